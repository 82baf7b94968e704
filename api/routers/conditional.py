"""Weak ETags and the cached JSON body of the polled read endpoints (``/chtc``, ``/chtc/map``, the field).

A body's part fixed by its ETag is serialised once per ETag and kept on ``app.state``; the two per-request
fields (``sample_age_s``, ``served_at``, the schema's last two) are appended to it. A 304 means "nothing
new"; a client that needs the current age computes it from ``newest_sample_at``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from datetime import datetime

from fastapi import Request, Response
from pydantic import BaseModel


def weak_etag(key: str) -> str:
    """A weak ETag (``W/"<16 hex>"``) of ``key``, the snapshot's fields that the body depends on."""
    return 'W/"' + hashlib.blake2b(key.encode(), digest_size=8).hexdigest() + '"'


def if_none_match(header: str | None, etag: str) -> bool:
    """Whether an ``If-None-Match`` header names ``etag`` (weak comparison, ``*`` matches all)."""
    if header is None:
        return False
    tags = {t.strip() for t in header.split(",")}
    return "*" in tags or etag in tags or etag.removeprefix("W/") in tags


def cached_json(
    request: Request,
    *,
    etag: str,
    slot: str,
    out: Callable[[], BaseModel],
    newest: datetime | None,
    now: datetime,
) -> Response:
    """304 when the request's ``If-None-Match`` names ``etag``; else the JSON of ``out()`` (serialised once
    per ETag, cached in ``app.state.<slot>``) with ``sample_age_s`` (from ``newest``) and ``served_at``."""
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if if_none_match(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    cached = getattr(request.app.state, slot, None)
    if cached is None or cached[0] != etag:
        fixed = out().model_dump_json(exclude={"sample_age_s", "served_at"})
        cached = (etag, fixed[:-1])
        setattr(request.app.state, slot, cached)
    age = "null" if newest is None else repr(round((now - newest).total_seconds(), 3))
    served = now.isoformat().replace("+00:00", "Z")
    body = f'{cached[1]},"sample_age_s":{age},"served_at":"{served}"}}'
    return Response(body, media_type="application/json", headers=headers)
