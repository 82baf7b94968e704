"""The real service over the simulated devices (real drivers, acquisition, core, worker process) at a
speed-up: with the DAQ hung, frozen or dropping connections, or the CAN node silent, `/readyz` turns not
ready within the documented limit naming the reason, and ready again when the device recovers (issue 12,
item 1; docs/design/service.md "Freshness"). Slow: about 40 s."""

from __future__ import annotations

import asyncio
import time

import pytest

from drivers.sim.faults import FaultKind
from model.plant import Segment
from service.host.runtime import Runtime, ScaledClock, free_port
from service.settings import Settings
from simulator.simrig import SimAddress, make_drivers, plant_rig

from .conftest import plant_run

pytestmark = pytest.mark.slow
SPEEDUP = 20.0


async def _until(pred, timeout_s: float, every_s: float = 0.05) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        await asyncio.sleep(every_s)
    return False


async def scenario(db_url: str) -> list[tuple[str, float, float, tuple[str, ...]]]:
    s = Settings()
    settings = s.model_copy(
        update={
            "api": s.api.model_copy(update={"port": free_port()}),
            "database": s.database.model_copy(update={"url": db_url}),
        }
    )
    clock = ScaledClock(SPEEDUP)
    runtime = Runtime(settings=settings, clock=clock, on_event=lambda _m: None)
    await asyncio.to_thread(runtime.load)
    address = SimAddress.free(speedup=SPEEDUP)
    daq, can_sensor = make_drivers(settings, address, clock=clock)
    run = plant_run([Segment(3600.0, 3000.0, 5.0, 22.0)], seed=6)
    driver_limit_s = daq.stale_after_s * SPEEDUP  # plant seconds the DAQ driver keeps its last good reading
    results = []
    rig = None
    try:
        await runtime.start(daq=daq, can=can_sensor, api=False)
        rig = await plant_rig(run, address=address)
        svc = runtime.service
        assert svc is not None
        assert await _until(lambda: svc.ready().ready, 30.0), svc.ready().reasons
        for name, faults, kind, extra_s in (
            ("daq hang", rig.daq_server.faults, FaultKind.HANG, driver_limit_s),
            ("daq freeze", rig.daq_server.faults, FaultKind.FREEZE, driver_limit_s),
            ("daq drop", rig.daq_server.faults, FaultKind.DROP, driver_limit_s),
            ("can silence", rig.can_node.faults, FaultKind.SILENCE, can_sensor.stale_after_s * SPEEDUP),
        ):
            t0 = clock()
            fault = faults.inject(kind)
            limit = extra_s + runtime.service.core.config.stale_after_s
            went = await _until(lambda: not svc.ready().ready, 2.0 * limit / SPEEDUP)
            elapsed = (clock() - t0).total_seconds()
            reasons = tuple(svc.ready().reasons)
            faults.clear(fault)
            results.append((name, elapsed if went else float("inf"), limit, reasons))
            assert await _until(lambda: svc.ready().ready, 60.0), (name, svc.ready().reasons)
    finally:
        await runtime.stop()
        if rig is not None:
            await rig.stop()
    return results


def test_device_failures_make_the_live_service_not_ready_within_the_limit(tmp_path) -> None:  # type: ignore[no-untyped-def]
    results = asyncio.run(scenario(f"sqlite:///{tmp_path / 'fresh.db'}"))
    for name, elapsed_s, limit_s, reasons in results:
        code = "can_no_good_data" if name.startswith("can") else "daq_no_good_data"
        assert elapsed_s <= limit_s + 20.0, (name, elapsed_s, limit_s, reasons)  # + 2 periods of slack
        assert any(r.startswith(code) for r in reasons), (name, reasons)
