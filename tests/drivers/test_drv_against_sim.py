"""Back to back: the drivers against the package's own simulated DAQ and CAN node with injected faults."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import Awaitable, Callable
from typing import TypeVar

import can
import numpy as np
import pytest

from drivers.can_sensor import CanSpindleSensor
from drivers.errors import (
    DeviceError,
    DeviceTimeoutError,
    ModbusExceptionError,
    ShortReplyError,
)
from drivers.modbus_daq import DaqReading, ModbusDaq
from drivers.quality import Quality
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import ArrayTimeline, TimelineSource

from .drvhelpers import FakeClock, poll_until

E = TypeVar("E", bound=BaseException)
TEMPS = np.round(np.linspace(18.0, 64.5, 32), 2)


async def _raises(kind: type[E], call: Callable[[], Awaitable[object]]) -> E:
    with pytest.raises(kind) as info:
        await call()
    return info.value


async def _recovered(daq: ModbusDaq, clock: FakeClock, *, timeout_s: float = 5.0) -> DaqReading:
    """Poll until a good reading arrives; the driver's backoff runs on ``clock``, stepped past each delay."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while True:
        assert asyncio.get_running_loop().time() < deadline, "driver did not recover"
        try:
            return await daq.read()
        except DeviceError:
            clock.advance(daq.retry_in_s())
            await asyncio.sleep(0.01)  # let the simulator's supervisor reopen its socket


def test_modbus_driver_against_simulated_daq_faults() -> None:
    async def main() -> None:
        source = TimelineSource(ArrayTimeline.constant(temps_c=TEMPS, ambient_c=22.5), speedup=1.0)
        faults = FaultController()
        async with SimulatedDaq(source, port=0, faults=faults, sample_period_s=0.05) as sim:
            clock = FakeClock()
            daq = ModbusDaq(
                sim.host, sim.port, timeout_s=0.2, stale_after_s=0.4, stuck_samples=None, clock=clock
            )
            async with daq:
                r = await daq.read()
                np.testing.assert_allclose(r.temps_c, TEMPS)
                assert r.ambient_c == pytest.approx(22.5) and set(r.quality.tolist()) == {Quality.OK}

                faults.inject(FaultKind.OPEN_CIRCUIT, channels=(5,))
                faults.inject(FaultKind.NAN, channels=(7,))
                faults.inject(FaultKind.OUT_OF_RANGE, channels=(9,))
                r = await daq.read()
                assert (r.quality[4], r.quality[6], r.quality[8]) == (
                    Quality.OPEN_CIRCUIT,
                    Quality.NAN,
                    Quality.OUT_OF_RANGE,
                )
                assert int(np.sum(r.quality == Quality.OK)) == 29
                faults.clear()

                faults.inject(FaultKind.EXCEPTION, value=4)
                err = await _raises(ModbusExceptionError, daq.read)
                assert err.exception_code == 4
                faults.clear()

                faults.inject(FaultKind.SHORT, value=3)
                assert (await _raises(ShortReplyError, daq.read)).got == 30
                faults.clear()

                faults.inject(FaultKind.GARBLED)
                assert "garbled" in str(await _raises(ShortReplyError, daq.read))
                faults.clear()
                await _recovered(daq, clock)

                faults.inject(FaultKind.HANG)
                await _raises(DeviceTimeoutError, daq.read)
                faults.clear()
                await _recovered(daq, clock)

                faults.inject(FaultKind.DROP)
                await poll_until(lambda: not sim.serving)
                await _raises(DeviceError, daq.read)  # lost connection or timeout, then refused
                faults.clear()
                r = await _recovered(daq, clock)
                assert set(r.quality.tolist()) == {Quality.OK}

                faults.inject(FaultKind.FREEZE)
                await daq.read()
                clock.advance(0.5)  # the device counter stays frozen for longer than stale_after_s
                r = await daq.read()
                assert set(r.quality.tolist()) == {Quality.STALE} and not r.new_sample
                faults.clear()
                fresh: list[DaqReading] = []

                async def read_fresh() -> None:
                    fresh.append(await daq.read())

                for _ in range(500):  # the simulator samples every 50 ms; bounded, not a bare sleep
                    await read_fresh()
                    if fresh[-1].new_sample:
                        break
                assert set(fresh[-1].quality.tolist()) == {Quality.OK}
            m = daq.metrics
            assert m.errors["ModbusExceptionError"] == 1 and m.errors["ShortReplyError"] == 2
            assert m.errors["DeviceTimeoutError"] >= 1 and m.reconnects >= 3

    asyncio.run(main())


def test_can_driver_against_simulated_node_faults() -> None:
    channel = f"drv-{uuid.uuid4().hex}"

    async def main() -> None:
        timeline = ArrayTimeline.constant(speed_rpm=4321.0, torque_nm=-3.21)
        source = TimelineSource(timeline, speedup=1.0)
        faults = FaultController()
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        sensor = CanSpindleSensor(interface="virtual", channel=channel, stale_after_s=0.2)
        await sensor.connect()
        task = asyncio.create_task(sensor.run(interval_s=0.0))
        try:
            async with SimulatedCanNode(source, bus=tx, faults=faults):
                await poll_until(lambda: sensor.metrics.reads_ok >= 5)
                r = sensor.current()
                assert (r.speed_rpm, r.torque_nm, r.quality) == (4321.0, -3.21, Quality.OK)

                faults.inject(FaultKind.COUNTER_GAP, value=3)
                await poll_until(lambda: sensor.metrics.events.get("counter_gaps", 0) == 1)
                assert sensor.metrics.events["frames_lost"] == 3
                faults.clear()

                for kind, error in [
                    (FaultKind.UNKNOWN_ID, "UnknownFrameIdError"),
                    (FaultKind.WRONG_DLC, "WrongDlcError"),
                ]:
                    faults.inject(kind)
                    await poll_until(lambda e=error: sensor.metrics.errors.get(e, 0) >= 2)
                    faults.clear()

                faults.inject(FaultKind.FAULT_STATUS)
                await poll_until(lambda: sensor.current().quality is Quality.FAULT)
                faults.clear()
                await poll_until(lambda: sensor.current().quality is Quality.OK)

                gaps_before = sensor.metrics.events.get("counter_gaps", 0)
                faults.inject(FaultKind.SILENCE)
                await poll_until(lambda: sensor.current().quality is Quality.STALE)
                faults.clear()
                await poll_until(lambda: sensor.current().quality is Quality.OK)
                assert (
                    sensor.metrics.events.get("counter_gaps", 0) == gaps_before
                )  # silence is no counter gap
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await sensor.close()
            tx.shutdown()

    asyncio.run(main())
