"""GET /chtc/map: the H map H = F(n, Ti) over the speed range (speed-map mode, docs/hmap.md), with its 95 %
bands, the speeds the fitted data have covered and how current the map is (cheap, with a weak ETag).

Per-condition mode (``identification.mode = "per_condition"``, the paper's protocol) has no map: 404
``not_found`` saying so. In speed-map mode before the first map fit: 503 ``no_data`` with ``Retry-After``.
The ETag covers what the snapshot says (the fit, status, ambient, current speed, newest sample), not
``served_at`` / ``sample_age_s``, as for ``/chtc``.
"""

from __future__ import annotations

import hashlib
from datetime import datetime

from fastapi import APIRouter, Request, Response

from api.deps import ClockDep, ReadAccess, ServiceDep
from api.errors import ApiError
from api.routers.chtc import _matches
from api.schemas import ChtcMapOut, chtc_map_out
from service.serve.interface import ChtcMapSnapshot

router = APIRouter(tags=["chtc"], dependencies=[ReadAccess])

PER_CONDITION = (
    "no speed map: identification.mode is per_condition (the paper's protocol, one H per held condition; "
    'GET /chtc serves it); set identification.mode = "speed_map" for H over the speed range'
)


def etag_of(s: ChtcMapSnapshot) -> str:
    key = f"{s.identification_id}|{s.fitted_at.isoformat()}|{s.family}|{s.restored}|{s.rmse_c}"
    key += f"|{s.status}|{s.reason}|{s.ambient_c!r}|{s.current_speed_rpm!r}|{s.newest_sample_at}"
    key += f"|{len(s.visited_rpm)}|{float(s.visited_s.sum())!r}|{len(s.speeds_rpm)}"
    return 'W/"' + hashlib.blake2b(key.encode(), digest_size=8).hexdigest() + '"'


@router.get(
    "/chtc/map",
    response_model=ChtcMapOut,
    responses={
        304: {"description": "not modified since the ETag"},
        404: {"description": "per-condition mode: the service fits no speed map"},
        503: {"description": "speed-map mode, but no map fitted yet"},
    },
    summary="H1-H7 over the speed range with 95 % bands, the visited speeds and the map's status",
)
async def get_chtc_map(request: Request, service: ServiceDep, clock: ClockDep) -> Response:
    snap = service.chtc_map()
    if snap is None:
        if service.identification_mode() == "per_condition":
            raise ApiError(status=404, code="not_found", message=PER_CONDITION)
        raise ApiError(
            status=503,
            code="no_data",
            message="no speed map fitted yet (the first fit needs the map's minimum window of data)",
            headers={"Retry-After": "5"},
        )
    etag = etag_of(snap)
    headers = {"ETag": etag, "Cache-Control": "no-cache"}
    if _matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    now = clock()
    return Response(_body(request, snap, etag, now), media_type="application/json", headers=headers)


def _body(request: Request, snap: ChtcMapSnapshot, etag: str, now: datetime) -> str:
    """The JSON body; the part fixed by the ETag (about 20 kB: 7 zones × 3 lists over the speed grid) is
    serialised once and the per-request ``sample_age_s`` and ``served_at`` (the schema's last two) are
    appended."""
    cached = getattr(request.app.state, "chtc_map_body", None)
    if cached is None or cached[0] != etag:
        fixed = chtc_map_out(snap, now).model_dump_json(exclude={"sample_age_s", "served_at"})
        cached = (etag, fixed[:-1])
        request.app.state.chtc_map_body = cached
    newest = snap.newest_sample_at
    age = "null" if newest is None else repr(round((now - newest).total_seconds(), 3))
    served = now.isoformat().replace("+00:00", "Z")
    return f'{cached[1]},"sample_age_s":{age},"served_at":"{served}"}}'
