"""GET /spindle: the spindle's named solid parts on the (r, z) section and its convective zones H1-H7."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from api.deps import ReadAccess, ServiceDep, SpindleIdDep
from api.schemas import SpindleAnswer

router = APIRouter(tags=["spindle"], dependencies=[ReadAccess])


class PartOut(BaseModel):
    name: str = Field(description='e.g. "housing", "front_end_cap", "rear_bearing"')
    material: str
    r0_m: float
    r1_m: float
    z0_m: float
    z1_m: float


class ZoneOut(BaseModel):
    name: str
    description: str


class SpindleOut(SpindleAnswer):
    name: str
    parts: list[PartOut] = Field(description="rectangles in (r, z), m; z from the rear (pulley) end")
    zones: list[ZoneOut]


@router.get("/spindle", response_model=SpindleOut, summary="named parts and convective zones of the section")
async def get_spindle(service: ServiceDep, spindle_id: SpindleIdDep) -> SpindleOut:
    lay = service.layout()
    return SpindleOut(
        spindle_id=spindle_id,
        name=lay.name,
        parts=[
            PartOut(name=p.name, material=p.material, r0_m=p.r0_m, r1_m=p.r1_m, z0_m=p.z0_m, z1_m=p.z1_m)
            for p in lay.parts
        ],
        zones=[ZoneOut(name=z.name, description=z.description) for z in lay.zones],
    )
