"""The running service's metrics (issue 12, item 15): the Modbus poll latency comes from the driver's own
timing of each poll, outcome counters hold one entry per poll / frame (so `outcome!="ok"` is a failure
rate), events have their own counters, and the current H, its CIs and the status are exported."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import numpy as np
import pytest

from drivers.base import Backoff, SourceMetrics
from drivers.errors import DeviceError
from drivers.modbus_daq import ModbusDaq
from drivers.registers import RegisterValues, default_register_map, encode
from service.core.machine import ServiceCore
from service.host.runtime import core_config
from service.settings import Settings
from service.shell.health import frame_events, frame_outcomes
from service.shell.service import SoftSensorService
from tests.drivers.drvhelpers import PymodbusDaqServer, free_port


def _can_stand_in() -> SimpleNamespace:
    m = SourceMetrics(polls=14, reads_ok=8)
    m.errors = {"UnknownFrameIdError": 2, "WrongDlcError": 1, "CounterGapError": 1, "DeviceTimeoutError": 3}
    m.events = {"frames": 11, "counter_gaps": 1, "frames_lost": 3, "faults": 2}
    return SimpleNamespace(metrics=m, connected=True, is_stale=lambda: False, condition=lambda: "")


def test_can_frame_outcomes_and_events_are_separate() -> None:
    can = _can_stand_in()
    # 11 frames: 8 accepted, 3 rejected; the counter gap was noticed on an accepted frame: an event
    assert frame_outcomes(can) == {"ok": 8, "unknown_frame_id": 2, "wrong_dlc": 1}
    assert sum(frame_outcomes(can).values()) == can.metrics.events["frames"]
    events = frame_events(can)
    assert events["counter_gaps"] == 1 and "counter_gap" not in events
    assert events["device_timeout"] == 3 and events["faults"] == 2  # silence is no frame


def test_modbus_latency_from_the_driver_and_one_outcome_per_poll(loaded_model) -> None:  # type: ignore[no-untyped-def]
    words = encode(
        default_register_map(), RegisterValues(np.full(32, 25.0), 21.0, np.zeros(32, np.int64), 0, 1)
    )

    async def main() -> tuple[SoftSensorService, ModbusDaq]:
        server = await PymodbusDaqServer(free_port(), words).start()
        daq = ModbusDaq("127.0.0.1", server.port, timeout_s=0.3, backoff=Backoff(initial_s=5.0, max_s=5.0))
        core = ServiceCore(core_config(Settings()), model=loaded_model)
        svc = SoftSensorService(core, worker=None, sources={"modbus": daq, "can": _can_stand_in()})
        for _ in range(5):
            await daq.read()
        server.hang.set()  # the device stops answering: a timeout, then polls refused until the backoff
        for _ in range(3):
            with pytest.raises(DeviceError):
                await daq.read()
        server.hang.clear()
        await daq.close()
        await server.stop()
        return svc, daq

    svc, daq = asyncio.run(main())
    m = svc.metrics()
    lat = m.modbus_poll_latency_s
    assert lat.count == 5 and 0.0 < lat.sum < 5 * 0.3  # the five good polls, each within the timeout
    assert m.modbus_polls_total == {"ok": 5, "device_timeout": 1, "link_down": 2}
    assert sum(m.modbus_polls_total.values()) == daq.metrics.polls
    assert m.modbus_events_total.get("new_samples") == 1  # the counter never advanced after the first
    assert "polls_while_down" not in m.modbus_events_total
    assert m.build_version and m.model_version == loaded_model.version
    assert m.chtc is None  # nothing identified yet: no H gauges
