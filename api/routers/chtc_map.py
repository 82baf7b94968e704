"""GET /chtc/map: the H map H = F(n, Ti) over the speed range (speed-map mode, docs/design/hmap.md), with its
95 % bands, the speeds the fitted data have covered and how current the map is (cheap, with a weak ETag).

Per-condition mode (``identification.mode = "per_condition"``, the paper's protocol) has no map: 404
``not_found`` saying so. In speed-map mode before the first map fit: 503 ``no_data`` with ``Retry-After``.
The ETag covers what the snapshot says (the fit, status, ambient, current speed, newest sample), not
``served_at`` / ``sample_age_s``, as for ``/chtc``.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep
from api.errors import ApiError
from api.routers.conditional import cached_json, weak_etag
from api.schemas import ChtcMapOut, chtc_map_out
from service.contracts.mode import IdentificationMode
from service.contracts.snapshots import ChtcMapSnapshot

router = APIRouter(tags=["chtc"], dependencies=[ReadAccess])

PER_CONDITION = (
    "no speed map: identification.mode is per_condition (the paper's protocol, one H per held condition; "
    'GET /chtc serves it); set identification.mode = "speed_map" for H over the speed range'
)


def etag_of(s: ChtcMapSnapshot) -> str:
    key = f"{s.identification_id}|{s.fitted_at.isoformat()}|{s.family}|{s.restored}|{s.rmse_c}"
    key += f"|{s.status}|{s.reason}|{s.ambient_c!r}|{s.current_speed_rpm!r}|{s.newest_sample_at}"
    key += f"|{len(s.visited_rpm)}|{float(s.visited_s.sum())!r}|{len(s.speeds_rpm)}"
    return weak_etag(key)


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
async def get_chtc_map(
    request: Request, service: ServiceDep, clock: ClockDep, spindle_id: SpindleIdDep
) -> Response:
    snap = service.chtc_map()
    if snap is None:
        if service.identification_mode() is IdentificationMode.PER_CONDITION:
            raise ApiError(status=404, code="not_found", message=PER_CONDITION)
        raise ApiError(
            status=503,
            code="no_data",
            message="no speed map fitted yet (the first fit needs the map's minimum window of data)",
            headers={"Retry-After": "5"},
        )
    now = clock()
    return cached_json(
        request,
        etag=etag_of(snap),
        slot="chtc_map_body",
        out=lambda: chtc_map_out(snap, now, spindle_id=spindle_id),
        newest=snap.newest_sample_at,
        now=now,
    )
