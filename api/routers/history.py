"""GET /sensors/history: measured vs predicted temperatures (°C) per sample, from the service's memory.

The service keeps the last ``capacity`` samples (6 h at the default 10 s period) with the live model's
prediction at each; a dashboard reload gets them back. A service restart empties it (the database stores the
measured samples, not the predictions).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, Field

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep, UtcDateTime
from api.errors import invalid
from api.routers.sensors import CHANNELS_PATTERN, parse_channels
from api.schemas import SpindleAnswer

router = APIRouter(tags=["sensors"], dependencies=[ReadAccess])

MAX_LIMIT = 10_000


class ChannelHistoryOut(BaseModel):
    channel: int
    name: str = Field(description="sensor name from the spindle description")
    role: str = Field(description='"bearing" | "housing" | "shaft" (a pyrometer aimed at the shaft)')
    measured_c: list[float | None] = Field(
        description="°C per sample; null = no usable value (quality not ok)"
    )
    predicted_c: list[float | None] = Field(description="°C per sample; null = no identification yet")


class SensorHistoryOut(SpindleAnswer):
    unit: str = "°C"
    since: datetime | None = Field(description="the query's since (UTC), samples are strictly later")
    served_at: datetime
    t: list[datetime] = Field(description="UTC sample times, oldest first")
    truncated: bool = Field(description="more samples matched than limit: only the newest limit are given")
    capacity: int = Field(description="samples the service keeps; older ones are gone")
    channels: list[ChannelHistoryOut]


def _values(column: np.ndarray) -> list[float | None]:
    return [round(float(v), 3) if np.isfinite(v) else None for v in column]


@router.get(
    "/sensors/history",
    response_model=SensorHistoryOut,
    summary="measured and predicted temperatures per sample (server-side history)",
)
async def get_sensor_history(
    service: ServiceDep,
    clock: ClockDep,
    spindle_id: SpindleIdDep,
    since: Annotated[UtcDateTime | None, Query(description="only samples after this UTC instant")] = None,
    channels: Annotated[
        str | None,
        Query(max_length=200, pattern=CHANNELS_PATTERN, description="comma-separated channel numbers 1..32"),
    ] = None,
    limit: Annotated[
        int, Query(ge=1, le=MAX_LIMIT, description="at most this many samples, the newest")
    ] = 2000,
) -> Response:
    hist = service.sensor_history(since)
    columns = list(range(len(hist.channels)))
    if channels is not None:
        chosen = parse_channels(channels)
        unknown = sorted(chosen - set(hist.channels))
        if unknown:
            known = f"{min(hist.channels)}-{max(hist.channels)}" if hist.channels else "none"
            raise invalid("channels", f"no channel {', '.join(map(str, unknown))} (channels: {known})")
        columns = [k for k, c in enumerate(hist.channels) if c in chosen]
    first = max(0, len(hist.t) - limit)
    out = SensorHistoryOut(
        spindle_id=spindle_id,
        since=since,
        served_at=clock(),
        t=list(hist.t[first:]),
        truncated=first > 0,
        capacity=hist.capacity,
        channels=[
            ChannelHistoryOut(
                channel=hist.channels[k],
                name=hist.names[k],
                role=hist.roles[k],
                measured_c=_values(hist.measured_c[first:, k]),
                predicted_c=_values(hist.predicted_c[first:, k]),
            )
            for k in columns
        ],
    )
    return Response(out.model_dump_json(), media_type="application/json")
