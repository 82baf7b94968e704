"""GET /compensation: the thermal growth at the tool for a compensation controller (docs/api.md,
docs/design/growth.md): axial and radial growth in µm and 0.1-µm integers, 95 % CIs, the forecast, the
controller values, the sensor sensitivity, with the policy's verdict on the growth
(``service.serve.policy``). GET /compensation/section: the section's outline and its displacement (µm) by
the live field, for the dashboard's exaggerated drawing.

A plain (not async) endpoint: FastAPI runs it in a worker thread, because the service may build the growth
model once and its per-condition terms (~0.3 s) on a new identification or condition; never on the loop.
"""

from __future__ import annotations

from fastapi import APIRouter

from api.deps import ClockDep, ReadAccess, ServiceDep
from api.errors import ApiError
from api.schemas import (
    CompensationOut,
    CompensationSectionOut,
    compensation_out,
    compensation_section_out,
)

router = APIRouter(tags=["compensation"], dependencies=[ReadAccess])


def _no_growth() -> ApiError:
    return ApiError(
        status=503,
        code="no_data",
        message="no identification or no live field yet",
        headers={"Retry-After": "5"},
    )


@router.get(
    "/compensation",
    response_model=CompensationOut,
    responses={503: {"description": "no identification or no live field yet"}},
    summary="thermal growth at the tool (µm, 0.1 µm), 95 % CI, forecast, controller values, status",
)
def get_compensation(service: ServiceDep, clock: ClockDep) -> CompensationOut:
    snap = service.compensation()
    if snap is None:
        raise _no_growth()
    return compensation_out(snap, clock())


@router.get(
    "/compensation/section",
    response_model=CompensationSectionOut,
    responses={503: {"description": "no identification or no live field yet"}},
    summary="the spindle's section outline and its displacement (u_r, u_z, µm) by the live field",
)
def get_compensation_section(service: ServiceDep, clock: ClockDep) -> CompensationSectionOut:
    snap = service.compensation_section()
    if snap is None:
        raise _no_growth()
    return compensation_section_out(snap, clock())
