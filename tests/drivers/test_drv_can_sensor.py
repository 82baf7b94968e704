"""CAN driver on python-can's ``virtual`` bus: decode, bad frames, counter gaps, faults, silence → stale."""

from __future__ import annotations

import asyncio
import threading
import uuid
from collections.abc import Awaitable, Callable

import can
import pytest

from drivers.base import Backoff
from drivers.can_codec import SensorStatus, encode_status
from drivers.can_sensor import CanReading, CanSpindleSensor
from drivers.errors import (
    BadSignalError,
    ConfigError,
    DeviceTimeoutError,
    DeviceUnavailableError,
    FrameError,
    NoDataError,
    UnknownFrameIdError,
    WrongDlcError,
)
from drivers.quality import Quality

from .drvhelpers import poll_until


def _frame(speed: float, torque: float, counter: int, status: int = 0) -> can.Message:
    return can.Message(
        arbitration_id=0x181, data=encode_status(speed, torque, counter, status), is_extended_id=False
    )


def _run(body: Callable[[can.BusABC, CanSpindleSensor], Awaitable[None]], **kwargs: object) -> None:
    channel = f"drv-{uuid.uuid4().hex}"

    async def main() -> None:
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        try:
            async with CanSpindleSensor(interface="virtual", channel=channel, **kwargs) as sensor:  # type: ignore[arg-type]
                await sensor.connect()
                await body(tx, sensor)
        finally:
            tx.shutdown()

    asyncio.run(main())


async def _read_all(sensor: CanSpindleSensor, n: int) -> list[CanReading | Exception]:
    out: list[CanReading | Exception] = []
    for _ in range(n):
        try:
            out.append(await sensor.read())
        except FrameError as err:
            out.append(err)
    return out


def test_decodes_frames_and_flags_gap_fault_and_bad_frames() -> None:
    async def body(tx: can.BusABC, sensor: CanSpindleSensor) -> None:
        tx.send(_frame(3000, 12.5, 0))
        tx.send(_frame(3010, 12.6, 1))
        tx.send(_frame(3020, 12.7, 4))  # counters 2 and 3 lost
        tx.send(can.Message(arbitration_id=0x200, data=b"\x00" * 8, is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x181, data=encode_status(1, 1, 5, 0)[:4], is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x181, data=encode_status(1, 1, 6, 9), is_extended_id=False))
        tx.send(_frame(3030, -1.25, 7, status=SensorStatus.WARNING))
        tx.send(_frame(3040, -1.5, 8, status=SensorStatus.FAULT))
        got = await _read_all(sensor, 8)
        r0, _r1, r2 = got[:3]
        assert isinstance(r0, CanReading) and (r0.speed_rpm, r0.torque_nm, r0.quality) == (
            3000,
            12.5,
            Quality.OK,
        )
        assert isinstance(r2, CanReading) and r2.frames_lost == 2
        assert isinstance(got[3], UnknownFrameIdError) and "0x200" in str(got[3])
        assert isinstance(got[4], WrongDlcError) and got[4].dlc == 4
        assert isinstance(got[5], BadSignalError)
        warn, fault = got[6], got[7]
        assert (
            isinstance(warn, CanReading)
            and warn.quality is Quality.OK
            and warn.status is SensorStatus.WARNING
        )
        assert isinstance(fault, CanReading) and fault.quality is Quality.FAULT and fault.torque_nm == -1.5
        m = sensor.metrics
        assert m.events["counter_gaps"] == 1 and m.events["frames_lost"] == 2
        assert m.events["faults"] == 1 and m.events["warnings"] == 1 and m.events["frames"] == 8
        assert m.errors["UnknownFrameIdError"] == 1 and m.errors["WrongDlcError"] == 1
        assert m.errors["CounterGapError"] == 1
        assert sensor.latest().counter == 8

    _run(body, stale_after_s=1.0)


def test_silence_marks_stale_and_frames_recover() -> None:
    async def body(tx: can.BusABC, sensor: CanSpindleSensor) -> None:
        with pytest.raises(NoDataError):
            sensor.current()
        tx.send(_frame(4000, 5.0, 3))
        assert (await sensor.read()).speed_rpm == 4000
        assert sensor.current().quality is Quality.OK
        with pytest.raises(DeviceTimeoutError, match="SpindleStatus frame"):
            await sensor.read()
        assert sensor.current().quality is Quality.STALE
        assert sensor.current().speed_rpm == 4000  # last value kept, flagged
        tx.send(_frame(4100, 5.0, 9))  # after silence, no bogus counter gap
        assert (await sensor.read()).frames_lost == 0
        assert sensor.current().quality is Quality.OK
        assert sensor.metrics.errors["DeviceTimeoutError"] == 1
        assert "counter_gaps" not in sensor.metrics.events

    _run(body, stale_after_s=0.2)


def test_run_loop_keeps_latest_and_counts() -> None:
    async def body(tx: can.BusABC, sensor: CanSpindleSensor) -> None:
        task = asyncio.create_task(sensor.run(interval_s=0.0))
        for k in range(40):
            tx.send(_frame(5000 + k, 2.0, k % 16))
        await poll_until(lambda: sensor.metrics.reads_ok >= 40)
        assert sensor.latest().speed_rpm == 5039
        assert "counter_gaps" not in sensor.metrics.events
        task.cancel()

    _run(body, stale_after_s=0.5)


def test_injected_bus_is_not_closed_and_never_written() -> None:
    channel = f"drv-{uuid.uuid4().hex}"

    class NoSendBus(can.interfaces.virtual.VirtualBus):  # type: ignore[misc]
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            raise AssertionError("the driver must never send")

    async def main() -> None:
        bus = NoSendBus(channel=channel)
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        async with CanSpindleSensor(bus=bus, stale_after_s=0.5) as sensor:
            await sensor.connect()
            tx.send(_frame(1234, 0.5, 0))
            assert (await sensor.read()).speed_rpm == 1234
        tx.send(_frame(1, 0.5, 1))
        assert bus.recv(1.0) is not None  # still open after the driver closed
        bus.shutdown()
        tx.shutdown()

    asyncio.run(main())


def test_unknown_interface_is_a_config_error() -> None:
    with pytest.raises(
        ConfigError, match=r"can\.interface: unknown python-can interface 'no-such-interface'"
    ):
        CanSpindleSensor(interface="no-such-interface", channel="x", backoff=Backoff(max_s=0.1))


def test_bus_error_reconnects_with_backoff() -> None:
    channel = f"drv-{uuid.uuid4().hex}"

    class FlakyBus(can.interfaces.virtual.VirtualBus):  # type: ignore[misc]
        fail = threading.Event()

        def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
            if self.fail.is_set():
                self.fail.clear()
                raise can.CanOperationError("interface went down")
            return super()._recv_internal(timeout)  # type: ignore[no-any-return]

    async def main() -> None:
        bus = FlakyBus(channel=channel)
        tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
        sensor = CanSpindleSensor(bus=bus, stale_after_s=0.5, backoff=Backoff(initial_s=0.05, max_s=0.1))
        errors: list[Exception] = []
        task = asyncio.create_task(sensor.run(interval_s=0.0, on_error=errors.append))
        try:
            await poll_until(lambda: sensor.connected)
            tx.send(_frame(100, 0.0, 0))
            await poll_until(lambda: sensor.metrics.reads_ok == 1)
            FlakyBus.fail.set()
            await poll_until(lambda: sensor.metrics.reconnects == 1)
            assert any(
                isinstance(e, DeviceUnavailableError) and "interface went down" in str(e) for e in errors
            )
            k = 1

            def delivered() -> bool:
                nonlocal k
                tx.send(_frame(200, 0.0, k % 16))
                k += 1
                return sensor.metrics.reads_ok >= 2

            await poll_until(delivered)
            assert sensor.latest().speed_rpm == 200
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await sensor.close()
            bus.shutdown()
            tx.shutdown()

    asyncio.run(main())


def test_inbox_overflow_drops_and_counts_frames() -> None:
    async def body(tx: can.BusABC, sensor: CanSpindleSensor) -> None:
        for k in range(20):
            tx.send(_frame(1000 + k, 0.0, k % 16))
        await poll_until(lambda: sensor._reader is not None and sensor._reader.dropped == 15)
        got = await _read_all(sensor, 5)
        assert [r.speed_rpm for r in got if isinstance(r, CanReading)] == [1000, 1001, 1002, 1003, 1004]
        assert sensor.metrics.events["frames_dropped"] == 15

    _run(body, stale_after_s=1.0, inbox_size=5)


def test_batched_wakeups_deliver_every_frame_in_order() -> None:
    async def body(tx: can.BusABC, sensor: CanSpindleSensor) -> None:
        for k in range(30):
            tx.send(_frame(2000 + k, 0.0, k % 16))
        got = await _read_all(sensor, 30)
        assert [r.speed_rpm for r in got if isinstance(r, CanReading)] == [2000.0 + k for k in range(30)]
        assert "counter_gaps" not in sensor.metrics.events
        tx.send(_frame(9, 0.0, 14))  # a lone frame still arrives (after at most batch_s)
        assert (await sensor.read()).speed_rpm == 9

    _run(body, stale_after_s=1.0, batch_s=0.05)
