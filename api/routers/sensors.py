"""GET /sensors: the 32 channels at the newest sample, measured vs predicted (°C), with the zeroed offsets.
POST /sensors/baseline (token): take a sensor-offset baseline now (service.acquire.calibration)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep, WriteAccess
from api.errors import ApiError, invalid
from api.schemas import BaselineOut, SensorsOut, baseline_out, sensor_out
from service.contracts.errors import NotReadyError

router = APIRouter(tags=["sensors"], dependencies=[ReadAccess])

# channel numbers 1..32 (the spindle's 32 sensors), comma-separated, e.g. 1,7,20
_CHANNEL = r"(?:[1-9]|[12][0-9]|3[0-2])"
CHANNELS_PATTERN = rf"^{_CHANNEL}(?:,{_CHANNEL})*$"


def parse_channels(text: str) -> set[int]:
    """``"1,2,17"`` -> {1, 2, 17}; a 422 naming ``channels`` otherwise."""
    try:
        chosen = {int(c) for c in text.split(",") if c.strip()}
    except ValueError:
        raise invalid("channels", f"{text!r} is not a comma-separated list of channel numbers") from None
    if not chosen or any(c < 1 for c in chosen):
        raise invalid("channels", "channel numbers start at 1")
    return chosen


def _only_known(chosen: set[int], known: set[int]) -> None:
    unknown = sorted(chosen - known)
    if unknown and known:
        raise invalid("channels", f"no channel {unknown[0]}; channels are {min(known)}..{max(known)}")


@router.get(
    "/sensors", response_model=SensorsOut, summary="newest sample per channel with the model prediction"
)
async def get_sensors(
    service: ServiceDep,
    clock: ClockDep,
    spindle_id: SpindleIdDep,
    channels: Annotated[
        str | None,
        Query(max_length=200, pattern=CHANNELS_PATTERN, description="comma-separated channel numbers 1..32"),
    ] = None,
) -> Response:
    readings = service.sensors()
    if channels is not None:
        chosen = parse_channels(channels)
        _only_known(chosen, {r.channel for r in readings})
        readings = [r for r in readings if r.channel in chosen]
    now = clock()
    newest = max((r.t for r in readings), default=None)
    out = SensorsOut(
        spindle_id=spindle_id,
        t=newest,
        sample_age_s=None if newest is None else round((now - newest).total_seconds(), 3),
        served_at=now,
        channels=[sensor_out(r) for r in readings],
    )
    return Response(out.model_dump_json(), media_type="application/json")


@router.post(
    "/sensors/baseline",
    response_model=BaselineOut,
    summary="take a sensor-offset baseline now (spindle at rest, at the ambient); 409 names why not",
)
def post_baseline(service: ServiceDep, _: WriteAccess) -> Response:  # waits for the core: a thread
    try:
        taken = service.request_baseline()
    except NotReadyError as err:  # the spindle's state refuses it (running, not at rest): a conflict
        raise ApiError(status=409, code="conflict", message=f"no baseline taken: {err}") from err
    out = baseline_out(taken)
    return Response(out.model_dump_json(), media_type="application/json")
