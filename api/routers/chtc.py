"""GET /chtc: the current H1-H7 (cheap enough for 10 Hz polling, with a weak ETag).

The ETag covers what the snapshot says (identification, status, condition, newest sample), not the
``served_at`` / ``sample_age_s`` fields that change with every request (``api.routers.conditional``).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep
from api.errors import ApiError
from api.routers.conditional import cached_json, weak_etag
from api.schemas import ChtcOut, chtc_out
from service.contracts.snapshots import ChtcSnapshot

router = APIRouter(tags=["chtc"], dependencies=[ReadAccess])


def etag_of(s: ChtcSnapshot) -> str:
    c = s.condition
    key = f"{s.identification_id}|{s.status}|{s.newest_sample_at}|{c.id}|{c.state}"
    key += f"|{s.model_version}|{s.reason}"
    key += "|" + ",".join(f"{f.channel}{f.kind}" for f in s.sensor_faults)
    return weak_etag(key)


@router.get(
    "/chtc",
    response_model=ChtcOut,
    responses={
        304: {"description": "not modified since the ETag"},
        503: {"description": "no identification yet"},
    },
    summary="current H1-H7 with 95 % CI, status and provenance",
)
async def get_chtc(
    request: Request, service: ServiceDep, clock: ClockDep, spindle_id: SpindleIdDep
) -> Response:
    snap = service.chtc()
    if snap is None:
        raise ApiError(
            status=503,
            code="no_data",
            message="no identification has finished yet",
            headers={"Retry-After": "5"},
        )
    now = clock()
    return cached_json(
        request,
        etag=etag_of(snap),
        slot="chtc_body",
        out=lambda: chtc_out(snap, now, spindle_id=spindle_id),
        newest=snap.newest_sample_at,
        now=now,
    )
