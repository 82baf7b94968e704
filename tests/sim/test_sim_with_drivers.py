"""The project's own drivers against the simulators: values round-trip and every fault arrives as the
documented error or quality flag (docs/design/simulation.md, SPEC §5)."""

from __future__ import annotations

import asyncio
import random
import time
import uuid
from collections.abc import Awaitable, Callable

import can
import numpy as np
import pytest

from drivers.base import Backoff
from drivers.can_codec import SensorStatus
from drivers.can_sensor import CanSpindleSensor
from drivers.errors import (
    DeviceTimeoutError,
    DeviceUnavailableError,
    ModbusExceptionError,
    ShortReplyError,
    UnknownFrameIdError,
    WrongDlcError,
)
from drivers.modbus_daq import ModbusDaq
from drivers.quality import Quality
from drivers.registers import RegisterEntry, RegisterMap
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import TimelineSource
from tests.sim.simhelpers import FakeClock, ramp_timeline

FAST = Backoff(initial_s=0.02, factor=2.0, max_s=0.1, jitter=0.0)


def _daq_session(
    body: Callable[[SimulatedDaq, ModbusDaq], Awaitable[None]],
    *,
    clock: FakeClock | None = None,
    register_map: RegisterMap | None = None,
) -> None:
    async def main() -> None:
        source = TimelineSource(ramp_timeline(), speedup=10.0, clock=clock or FakeClock())
        async with SimulatedDaq(source, port=0, register_map=register_map) as sim:
            daq = ModbusDaq(
                "127.0.0.1",
                sim.port,
                register_map=register_map,
                timeout_s=0.3,
                backoff=FAST,
                rng=random.Random(0),
            )
            try:
                await body(sim, daq)
            finally:
                await daq.close()

    asyncio.run(main())


def _float_map(order: str) -> RegisterMap:
    entries = [
        RegisterEntry(f"T{c:02d}", 2 * (c - 1), "float32", 1.0, order, "housing", c) for c in range(1, 33)
    ]  # type: ignore[arg-type]
    entries.append(RegisterEntry("amb", 64, "float32", 1.0, order, "ambient", None))  # type: ignore[arg-type]
    entries += [RegisterEntry(f"S{c:02d}", 99 + c, "uint16", 1.0, "big", "status", c) for c in range(1, 33)]
    entries.append(RegisterEntry("n", 300, "uint32", 1.0, "little", "counter", None))
    return RegisterMap(tuple(entries), unit_id=7, n_channels=32)


@pytest.mark.parametrize(
    "reg_map", [None, _float_map("big"), _float_map("little")], ids=["int16", "f32big", "f32little"]
)
def test_driver_reads_the_timeline(reg_map: RegisterMap | None) -> None:
    clock = FakeClock()

    async def body(sim: SimulatedDaq, daq: ModbusDaq) -> None:
        clock.advance(3.0)  # sim 30 s
        reading = await daq.read()
        expected = sim.source.at(30.0)
        if reg_map is None:
            np.testing.assert_allclose(reading.temps_c, expected.temps_c, atol=0.005 + 1e-9)
        else:
            np.testing.assert_array_equal(reading.temps_c, expected.temps_c.astype(np.float32))
        assert reading.ambient_c == pytest.approx(expected.ambient_c, abs=0.006)
        assert reading.counter == 30
        assert (reading.quality == Quality.OK).all()

    _daq_session(body, clock=clock, register_map=reg_map)


def test_channel_faults_become_quality_flags() -> None:
    async def body(sim: SimulatedDaq, daq: ModbusDaq) -> None:
        sim.faults.inject(FaultKind.OPEN_CIRCUIT, channels=(2,))
        sim.faults.inject(FaultKind.OUT_OF_RANGE, channels=(4,))
        sim.faults.inject(FaultKind.NAN, channels=(6,))
        q = (await daq.read()).quality
        assert (q[1], q[3], q[5]) == (Quality.OPEN_CIRCUIT, Quality.OUT_OF_RANGE, Quality.NAN)
        assert int((q == Quality.OK).sum()) == 29

    _daq_session(body)


def test_protocol_faults_become_typed_errors() -> None:
    async def body(sim: SimulatedDaq, daq: ModbusDaq) -> None:
        await daq.read()
        f = sim.faults.inject(FaultKind.EXCEPTION, value=4)
        with pytest.raises(ModbusExceptionError) as info:
            await daq.read()
        assert info.value.exception_code == 4
        sim.faults.clear(f)
        f = sim.faults.inject(FaultKind.SHORT)
        with pytest.raises(ShortReplyError):
            await daq.read()
        sim.faults.clear(f)
        f = sim.faults.inject(FaultKind.GARBLED)
        with pytest.raises(ShortReplyError, match="garbled reply"):
            await daq.read()
        sim.faults.clear(f)
        await _until_ok(daq)
        f = sim.faults.inject(FaultKind.GARBLED, value=2)  # pymodbus drops the link on this one
        with pytest.raises((ShortReplyError, DeviceUnavailableError)):
            await daq.read()
        sim.faults.clear(f)
        await _until_ok(daq)

    _daq_session(body)


async def _until_ok(daq: ModbusDaq, timeout: float = 5.0) -> float:
    """Poll the driver until a read succeeds; returns the seconds it took."""
    t0 = time.monotonic()
    while True:
        try:
            await daq.read()
            return time.monotonic() - t0
        except (DeviceTimeoutError, DeviceUnavailableError, ShortReplyError):
            if time.monotonic() - t0 > timeout:
                raise
            await asyncio.sleep(0.01)


@pytest.mark.parametrize("kind", [FaultKind.HANG, FaultKind.DROP])
def test_outage_is_reported_and_the_driver_recovers(kind: FaultKind) -> None:
    expected = DeviceTimeoutError if kind == FaultKind.HANG else DeviceUnavailableError

    async def body(sim: SimulatedDaq, daq: ModbusDaq) -> None:
        await daq.read()
        sim.faults.inject(kind)
        t0 = time.monotonic()
        while True:  # a drop takes effect within one supervisor period (20 ms)
            try:
                await daq.read()
            except expected:
                break
            assert time.monotonic() - t0 < 5.0, "fault never observed"
            await asyncio.sleep(0.01)
        sim.faults.clear(kind)
        assert await _until_ok(daq) < 2.0
        assert daq.metrics.reconnects >= 1

    _daq_session(body)


def test_frozen_counter_goes_stale() -> None:
    clock = FakeClock()

    async def body(sim: SimulatedDaq, daq: ModbusDaq) -> None:
        daq._clock = clock  # the driver's staleness runs on the same injected clock
        await daq.read()
        sim.faults.inject(FaultKind.FREEZE)
        clock.advance(40.0)
        reading = await daq.read()
        assert not reading.new_sample
        assert (reading.quality == Quality.STALE).all()

    _daq_session(body, clock=clock)


# -------------------------------------------------------------------------------------------------- CAN
def _can_session(body: Callable[[SimulatedCanNode, CanSpindleSensor], Awaitable[None]]) -> None:
    channel = f"drv-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)

    async def main() -> None:
        sensor = CanSpindleSensor(bus=rx, stale_after_s=0.3)
        try:
            async with SimulatedCanNode(TimelineSource(ramp_timeline(), speedup=10.0), bus=tx) as node:
                await body(node, sensor)
        finally:
            await sensor.close()

    try:
        asyncio.run(main())
    finally:
        tx.shutdown()
        rx.shutdown()


async def _read_until(
    sensor: CanSpindleSensor, want: type[Exception] | None, pred: Callable[[object], bool]
) -> object:
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        try:
            reading = await sensor.read()
        except Exception as err:
            if want is not None and isinstance(err, want):
                return err
            raise
        if want is None and pred(reading):
            return reading
    raise AssertionError("expected reading/error not seen")


def test_can_driver_sees_values_and_each_fault() -> None:
    async def body(node: SimulatedCanNode, sensor: CanSpindleSensor) -> None:
        first = await sensor.read()
        assert 1000.0 <= first.speed_rpm <= 5000.0 and first.frames_lost == 0
        node.faults.inject(FaultKind.COUNTER_GAP, value=5)
        gap = await _read_until(sensor, None, lambda r: r.frames_lost > 0)  # type: ignore[attr-defined]
        assert gap.frames_lost == 5  # type: ignore[attr-defined]
        node.faults.clear()
        node.faults.inject(FaultKind.FAULT_STATUS)
        faulted = await _read_until(sensor, None, lambda r: r.status == SensorStatus.FAULT)  # type: ignore[attr-defined]
        assert faulted.quality == Quality.FAULT  # type: ignore[attr-defined]
        node.faults.clear()
        node.faults.inject(FaultKind.WRONG_DLC)
        await _read_until(sensor, WrongDlcError, lambda r: False)
        node.faults.clear()
        node.faults.inject(FaultKind.UNKNOWN_ID)
        await _read_until(sensor, UnknownFrameIdError, lambda r: False)
        node.faults.clear()
        node.faults.inject(FaultKind.SILENCE)
        await _read_until(sensor, DeviceTimeoutError, lambda r: False)
        node.faults.clear()
        back = await _read_until(sensor, None, lambda r: True)
        assert back.quality == Quality.OK  # type: ignore[attr-defined]

    _can_session(body)
