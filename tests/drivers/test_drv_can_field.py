"""CAN driver against the simulated sensor node on python-can virtual buses: fault/warning status is a named
condition, rejected frames are not counted as lost, CAN FD / extended / remote frames with ID 0x181 are
rejected, and any python-can interface is accepted with its options passed through."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import can
import pytest

from drivers.can_sensor import CanReading, CanSpindleSensor
from drivers.errors import BadSignalError, ConfigError, DeviceTimeoutError, FrameError, UnknownFrameIdError
from drivers.quality import Quality
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultController, FaultKind
from drivers.sim.source import ArrayTimeline, TimelineSource


@asynccontextmanager
async def _rig(**sensor_kw: Any) -> AsyncIterator[tuple[CanSpindleSensor, FaultController]]:
    """A simulated node sending every 10 ms on a fresh virtual channel, and the driver listening to it."""
    channel = f"field-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    faults = FaultController()
    source = TimelineSource(ArrayTimeline.constant(speed_rpm=3000.0, torque_nm=5.0))
    try:
        async with CanSpindleSensor(
            interface="virtual", channel=channel, stale_after_s=1.0, **sensor_kw
        ) as s:
            await s.connect()
            async with SimulatedCanNode(source, bus=tx, faults=faults):
                yield s, faults
    finally:
        tx.shutdown()


async def _read(sensor: CanSpindleSensor, n: int) -> list[CanReading | FrameError]:
    out: list[CanReading | FrameError] = []
    for _ in range(n):
        try:
            out.append(await sensor.read())
        except FrameError as err:
            out.append(err)
    return out


@pytest.mark.parametrize(("value", "word"), [(2, "fault"), (1, "warning")])
def test_fault_and_warning_status_are_a_named_condition_and_clear(value: int, word: str) -> None:
    async def main() -> None:
        async with _rig() as (sensor, faults):
            await _read(sensor, 3)
            assert sensor.condition() == ""
            fault = faults.inject(FaultKind.FAULT_STATUS, value=value)
            got = await _read(sensor, 3)  # at most one frame of the old status was already on its way
            assert isinstance(got[-1], CanReading) and got[-1].status == value
            assert f"sensor reports {word} (status byte {value})" in sensor.condition()
            assert (got[-1].quality is Quality.FAULT) == (value == 2)
            faults.clear(fault)
            await _read(sensor, 3)
            assert sensor.condition() == ""

    asyncio.run(main())


def test_frames_rejected_for_a_bad_status_byte_or_dlc_are_not_counted_lost() -> None:
    async def main() -> None:
        async with _rig() as (sensor, faults):
            await _read(sensor, 3)
            bad = faults.inject(FaultKind.FAULT_STATUS, value=9)
            got = await _read(sensor, 6)
            assert sum(isinstance(g, BadSignalError) for g in got) >= 5
            faults.clear(bad)
            short = faults.inject(FaultKind.WRONG_DLC, value=3)  # too short to hold the counter
            await _read(sensor, 6)
            faults.clear(short)
            long = faults.inject(FaultKind.WRONG_DLC, value=8)
            await _read(sensor, 6)
            faults.clear(long)
            got = await _read(sensor, 6)
            assert all(isinstance(g, CanReading) for g in got[1:])
            m = sensor.metrics
            assert m.errors["BadSignalError"] >= 5 and m.errors["WrongDlcError"] >= 10
            assert m.events.get("frames_lost", 0) == 0 and m.events.get("counter_gaps", 0) == 0
            assert "CounterGapError" not in m.errors

    asyncio.run(main())


def test_a_real_gap_is_still_counted_after_rejected_frames() -> None:
    async def main() -> None:
        async with _rig() as (sensor, faults):
            await _read(sensor, 3)
            bad = faults.inject(FaultKind.FAULT_STATUS, value=9)
            await _read(sensor, 3)
            faults.clear(bad)
            faults.inject(FaultKind.COUNTER_GAP, value=3)
            got = await _read(sensor, 4)
            lost = [g.frames_lost for g in got if isinstance(g, CanReading)]
            assert 3 in lost and sensor.metrics.events["frames_lost"] == 3

    asyncio.run(main())


@pytest.mark.parametrize(
    ("kind", "error", "text"),
    [
        (FaultKind.FD_FRAME, FrameError, "CAN FD frame (the contract is CAN 2.0A)"),
        (FaultKind.EXTENDED_ID, UnknownFrameIdError, "unknown extended ID"),
        (FaultKind.REMOTE_FRAME, FrameError, "remote frame"),
    ],
)
def test_fd_extended_and_remote_frames_with_id_0x181_are_rejected(
    kind: FaultKind, error: type[FrameError], text: str
) -> None:
    async def main() -> None:
        async with _rig() as (sensor, faults):
            await _read(sensor, 2)
            faults.inject(kind)
            got = await _read(sensor, 8)
            rejected = [g for g in got if isinstance(g, FrameError)]
            assert rejected and all(type(g) is error and "0x181" in str(g) for g in rejected)
            assert all(text in str(g) for g in rejected)
            accepted = [g for g in got[2:] if isinstance(g, CanReading)]
            if kind is not FaultKind.REMOTE_FRAME:  # the status frame itself is the bad one
                assert accepted == []

    asyncio.run(main())


def test_any_python_can_interface_with_options_passed_through() -> None:
    calls: list[dict[str, Any]] = []

    def factory(**kwargs: Any) -> can.BusABC:
        calls.append(kwargs)
        return can.Bus(interface="virtual", channel="opts", ignore_config=True)

    filters = [{"can_id": 0x181, "can_mask": 0x7FF, "extended": False}]
    sensor = CanSpindleSensor(
        interface="pcan",
        channel="PCAN_USBBUS1",
        bitrate=500_000,
        fd=True,
        data_bitrate=2_000_000,
        can_filters=filters,
        bus_kwargs={"auto_reset": True},
        bus_factory=factory,
    )

    async def main() -> None:
        await sensor.connect()
        await sensor.close()

    asyncio.run(main())
    assert calls == [
        {
            "interface": "pcan",
            "channel": "PCAN_USBBUS1",
            "ignore_config": True,
            "bitrate": 500_000,
            "fd": True,
            "data_bitrate": 2_000_000,
            "can_filters": filters,
            "auto_reset": True,
        }
    ]
    for name in ("kvaser", "vector", "ixxat", "slcan", "socketcand", "socketcan", "remote"):
        CanSpindleSensor(interface=name, channel="x")
    with pytest.raises(ConfigError, match=r"can\.interface"):
        CanSpindleSensor(interface="peak", channel="x")


def test_filters_reach_a_real_virtual_bus() -> None:
    async def main() -> None:
        only_0x200 = [{"can_id": 0x200, "can_mask": 0x7FF, "extended": False}]
        async with _rig(can_filters=only_0x200) as (sensor, _faults):
            with pytest.raises(DeviceTimeoutError):
                await sensor.read()  # the node sends 0x181 every 10 ms; the bus filters it out
        async with _rig(can_filters=[{"can_id": 0x181, "can_mask": 0x7FF}]) as (sensor, _faults):
            assert isinstance(await sensor.read(), CanReading)

    asyncio.run(main())


@pytest.mark.parametrize(
    ("exc", "text"),
    [
        (
            NameError("name 'canGetNumberOfChannels' is not defined"),
            "NameError: name 'canGetNumberOfChannels'",
        ),
        (TypeError("__init__() missing 2 required positional arguments: 'host' and 'port'"), "TypeError"),
        (can.CanInterfaceNotImplementedError("The serial module is not installed"), "not usable here"),
        (OSError("pcanbasic library not found"), "OSError: pcanbasic library not found"),
    ],
)
def test_a_bus_that_cannot_be_opened_is_named_and_retried(exc: Exception, text: str) -> None:
    from drivers.base import Backoff
    from drivers.errors import DeviceUnavailableError

    def factory(**_kwargs: Any) -> can.BusABC:
        raise exc

    async def main() -> None:
        sensor = CanSpindleSensor(
            interface="kvaser", channel="0", bus_factory=factory, backoff=Backoff(initial_s=0.01, max_s=0.01)
        )
        for _ in range(2):
            with pytest.raises(DeviceUnavailableError, match=text):
                await sensor.connect()
            await asyncio.sleep(0.02)
        assert sensor.metrics.connect_failures == 2
        await sensor.close()

    asyncio.run(main())
