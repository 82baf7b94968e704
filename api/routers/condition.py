"""GET /condition: the current operating condition and the recent ones (condition timeline)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep
from api.schemas import ConditionsOut, condition_out

router = APIRouter(tags=["condition"], dependencies=[ReadAccess])


@router.get("/condition", response_model=ConditionsOut, summary="current operating condition and recent ones")
async def get_condition(
    service: ServiceDep,
    clock: ClockDep,
    spindle_id: SpindleIdDep,
    limit: Annotated[int, Query(ge=1, le=100, description="how many recent conditions")] = 20,
) -> ConditionsOut:
    current = service.condition()
    recent = service.recent_conditions(limit)
    return ConditionsOut(
        spindle_id=spindle_id,
        current=condition_out(current),
        recent=[condition_out(c) for c in recent],
        served_at=clock(),
    )
