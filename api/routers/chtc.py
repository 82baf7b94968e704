"""GET /chtc: the current H1-H7 (cheap enough for 10 Hz polling, with a weak ETag).

The ETag covers what the snapshot says (identification, status, condition, newest sample), not the
``served_at`` / ``sample_age_s`` fields that change with every request: a 304 means "nothing new"; a client
that needs the current age computes it from ``newest_sample_at``.
"""

from __future__ import annotations

import hashlib
from datetime import datetime

from fastapi import APIRouter, Request, Response

from api.deps import ClockDep, ReadAccess, ServiceDep
from api.errors import ApiError
from api.schemas import ChtcOut, chtc_out
from service.serve.interface import ChtcSnapshot

router = APIRouter(tags=["chtc"], dependencies=[ReadAccess])


def etag_of(s: ChtcSnapshot) -> str:
    c = s.condition
    key = f"{s.identification_id}|{s.status}|{s.newest_sample_at}|{c.id}|{c.state}"
    key += f"|{s.model_version}|{s.reason}"
    return 'W/"' + hashlib.blake2b(key.encode(), digest_size=8).hexdigest() + '"'


def _matches(header: str | None, etag: str) -> bool:
    if header is None:
        return False
    tags = {t.strip() for t in header.split(",")}
    return "*" in tags or etag in tags or etag.removeprefix("W/") in tags


@router.get(
    "/chtc",
    response_model=ChtcOut,
    responses={
        304: {"description": "not modified since the ETag"},
        503: {"description": "no identification yet"},
    },
    summary="current H1-H7 with 95 % CI, status and provenance",
)
async def get_chtc(request: Request, service: ServiceDep, clock: ClockDep) -> Response:
    snap = service.chtc()
    if snap is None:
        raise ApiError(
            status=503,
            code="no_data",
            message="no identification has finished yet",
            headers={"Retry-After": "5"},
        )
    etag = etag_of(snap)
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if _matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    now = clock()
    return Response(_body(request, snap, etag, now), media_type="application/json", headers=headers)


def _body(request: Request, snap: ChtcSnapshot, etag: str, now: datetime) -> str:
    """The JSON body; the part fixed by the ETag is serialised once and the two per-request fields
    (``sample_age_s``, ``served_at``, the schema's last two) are appended."""
    cached = getattr(request.app.state, "chtc_body", None)
    if cached is None or cached[0] != etag:
        fixed = chtc_out(snap, now).model_dump_json(exclude={"sample_age_s", "served_at"})
        cached = (etag, fixed[:-1])
        request.app.state.chtc_body = cached
    newest = snap.newest_sample_at
    age = "null" if newest is None else repr(round((now - newest).total_seconds(), 3))
    served = now.isoformat().replace("+00:00", "Z")
    return f'{cached[1]},"sample_age_s":{age},"served_at":"{served}"}}'
