"""Acquisition: combining DAQ + CAN into samples, sampler timing on an injected clock, end to end."""

from __future__ import annotations

import asyncio
import math
import uuid
from datetime import UTC, datetime, timedelta

import can
import numpy as np
import pytest

from drivers.acquisition import Acquisition, combine
from drivers.can_codec import SensorStatus, encode_status
from drivers.can_sensor import CanReading, CanSpindleSensor
from drivers.errors import NoDataError
from drivers.modbus_daq import DaqReading, ModbusDaq
from drivers.quality import Quality
from drivers.registers import RegisterValues, default_register_map, encode
from drivers.ringbuffer import RingBuffer, Sample

from .drvhelpers import FakeClock, PymodbusDaqServer, free_port, poll_until

T0 = datetime(2026, 3, 1, 12, tzinfo=UTC)


def _daq(quality: Quality = Quality.OK, ambient_q: Quality = Quality.OK) -> DaqReading:
    return DaqReading(
        T0,
        np.arange(32.0),
        21.5,
        np.zeros(32, dtype=np.int64),
        7,
        np.full(32, np.uint8(quality)),
        ambient_quality=ambient_q,
    )


def _can(quality: Quality = Quality.OK, status: SensorStatus = SensorStatus.OK) -> CanReading:
    return CanReading(T0, 3000.0, 12.5, status, 3, quality=quality)


def test_combine_rules() -> None:
    s = combine(_daq(), _can(), t=T0, n_channels=32)
    assert (s.ambient_c, s.speed_rpm, s.torque_nm, s.daq_ok, s.can_ok) == (21.5, 3000.0, 12.5, True, True)
    none = combine(None, None, t=T0, n_channels=32)
    assert np.isnan(none.temps_c).all() and set(none.quality.tolist()) == {Quality.NO_DATA}
    assert math.isnan(none.speed_rpm) and not none.daq_ok and not none.can_ok
    stale = combine(_daq(Quality.STALE, Quality.STALE), _can(Quality.STALE), t=T0, n_channels=32)
    assert not stale.daq_ok and not stale.can_ok and stale.temps_c[3] == 3.0 and math.isnan(stale.ambient_c)
    assert not combine(_daq(), _can(Quality.FAULT, SensorStatus.FAULT), t=T0, n_channels=32).can_ok
    assert combine(_daq(), _can(status=SensorStatus.WARNING), t=T0, n_channels=32).can_ok
    assert math.isnan(combine(_daq(ambient_q=Quality.OPEN_CIRCUIT), None, t=T0, n_channels=32).ambient_c)


class _Fixed:
    def __init__(self, reading: object) -> None:
        self.reading = reading

    def current(self) -> object:
        if self.reading is None:
            raise NoDataError("nothing yet")
        return self.reading

    async def run(self, *, interval_s: float) -> None:
        await asyncio.Event().wait()


class _Stop(Exception):
    pass


def test_sampler_ticks_on_injected_clock_without_drift() -> None:
    clock = FakeClock(t=0.0)
    ring = RingBuffer(100)
    seen: list[Sample] = []

    async def slow_sleep(s: float) -> None:
        clock.advance(s + 0.3)  # the loop wakes late every time; ticks must not drift

    def on_sample(s: Sample) -> None:
        seen.append(s)
        if len(seen) == 6:
            raise _Stop

    acq = Acquisition(
        _Fixed(_daq()),
        _Fixed(None),
        ring,
        period_s=10.0,
        on_sample=on_sample,
        clock=clock,
        now=lambda: T0 + timedelta(seconds=clock()),
        sleep=slow_sleep,
    )  # type: ignore[arg-type]
    with pytest.raises(_Stop):
        asyncio.run(acq.run_sampler())
    offsets = [(s.t - T0).total_seconds() for s in seen]
    assert offsets == pytest.approx([10.3 + 10 * k for k in range(6)])
    assert len(ring) == 6 and not ring.latest().can_ok and math.isnan(ring.latest().speed_rpm)


def test_end_to_end_modbus_and_can_into_ring() -> None:
    reg_map = default_register_map()
    temps = np.linspace(20.0, 51.0, 32)
    words = encode(reg_map, RegisterValues(temps, 22.0, np.zeros(32, dtype=np.int64), 0, 1))
    channel = f"drv-{uuid.uuid4().hex}"

    async def main() -> None:
        server = await PymodbusDaqServer(free_port(), words).start()
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        daq = ModbusDaq("127.0.0.1", server.port, timeout_s=0.5)
        sensor = CanSpindleSensor(interface="virtual", channel=channel, stale_after_s=1.0)
        ring = RingBuffer(1000)
        acq = Acquisition(daq, sensor, ring, period_s=0.05)
        await sensor.connect()
        task = asyncio.create_task(acq.run(poll_interval_s=0.02))
        try:
            k = 0

            def ready() -> bool:
                nonlocal k
                tx.send(
                    can.Message(
                        arbitration_id=0x181, data=encode_status(4500, 7.25, k % 16, 0), is_extended_id=False
                    )
                )
                k += 1
                return len(ring) >= 3 and ring.latest().daq_ok and ring.latest().can_ok

            await poll_until(ready, timeout_s=10)
            s = ring.latest()
            np.testing.assert_allclose(s.temps_c, temps)
            assert (s.ambient_c, s.speed_rpm, s.torque_nm) == (pytest.approx(22.0), 4500.0, 7.25)
            assert set(s.quality.tolist()) == {Quality.OK}
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await daq.close()
            await sensor.close()
            tx.shutdown()
            await server.stop()

    asyncio.run(main())
