"""Simulated CAN node on a python-can virtual bus: decoded values, counter continuity, faults."""

from __future__ import annotations

import asyncio
import itertools
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from drivers.can_codec import SPINDLE_STATUS_ID, SensorStatus, counter_gap, decode_frame
from drivers.errors import UnknownFrameIdError, WrongDlcError
from drivers.sim.can_hub import CanHub
from drivers.sim.can_node import SimulatedCanNode
from drivers.sim.faults import FaultKind
from drivers.sim.source import TimelineSource
from tests.sim.simhelpers import FakeClock, ramp_timeline


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = f"sim-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    rx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


def _collect(rx: can.BusABC, n: int, timeout: float = 5.0) -> list[can.Message]:
    out: list[can.Message] = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        msg = rx.recv(timeout=0.1)
        if msg is not None:
            out.append(msg)
    return out


def test_node_sends_decodable_frames_with_a_continuous_counter(buses: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = buses
    clock = FakeClock()
    source = TimelineSource(ramp_timeline(), speedup=10.0, clock=clock)
    clock_steps = [0.0]

    async def main() -> list[can.Message]:
        async with SimulatedCanNode(source, bus=tx) as node:
            clock.advance(2.5)  # sim 25 s: speed 2000 rpm, torque 3 N·m
            clock_steps.append(node.period_s)
            return await asyncio.to_thread(_collect, rx, 40)

    frames = asyncio.run(main())
    assert len(frames) == 40
    decoded = [decode_frame(m.arbitration_id, m.data) for m in frames]
    gaps = [counter_gap(a.counter, b.counter) for a, b in itertools.pairwise(decoded)]
    assert gaps == [0] * 39
    last = decoded[-1]
    assert last.speed_rpm == pytest.approx(2000.0)
    assert last.torque_nm == pytest.approx(3.0)
    assert last.status == SensorStatus.OK
    assert clock_steps[1] == pytest.approx(0.010)  # 10 ms sim at 10x is 1 ms: capped at 10 ms wall


def _node(clock: FakeClock, bus: can.BusABC) -> SimulatedCanNode:
    return SimulatedCanNode(TimelineSource(ramp_timeline(), clock=clock), bus=bus)


def test_counter_gap_once_per_activation(buses: tuple[can.BusABC, can.BusABC]) -> None:
    node = _node(FakeClock(), buses[0])
    counters = [decode_frame(m.arbitration_id, m.data).counter for _ in range(3) for m in node.frames()]
    node.faults.inject(FaultKind.COUNTER_GAP, value=4)
    counters += [decode_frame(m.arbitration_id, m.data).counter for _ in range(3) for m in node.frames()]
    gaps = [counter_gap(a, b) for a, b in itertools.pairwise(counters)]
    assert gaps == [0, 0, 4, 0, 0]


def test_unknown_id_wrong_dlc_fault_status_and_silence(buses: tuple[can.BusABC, can.BusABC]) -> None:
    node = _node(FakeClock(), buses[0])
    node.faults.inject(FaultKind.UNKNOWN_ID, value=0x555)
    ids = [m.arbitration_id for m in node.frames()]
    assert ids == [SPINDLE_STATUS_ID, 0x555]
    with pytest.raises(UnknownFrameIdError):
        decode_frame(0x555, node.frames()[1].data)
    node.faults.clear()
    node.faults.inject(FaultKind.WRONG_DLC, value=3)
    (frame,) = node.frames()
    assert frame.dlc == 3
    with pytest.raises(WrongDlcError):
        decode_frame(frame.arbitration_id, frame.data)
    node.faults.clear()
    node.faults.inject(FaultKind.FAULT_STATUS)
    (frame,) = node.frames()
    assert decode_frame(frame.arbitration_id, frame.data).status == SensorStatus.FAULT
    node.faults.clear()
    node.faults.inject(FaultKind.SILENCE)
    assert node.frames() == []


def test_silence_is_seen_on_the_bus_and_ends(buses: tuple[can.BusABC, can.BusABC]) -> None:
    tx, rx = buses
    source = TimelineSource(ramp_timeline())

    async def main() -> tuple[int, int]:
        async with SimulatedCanNode(source, bus=tx) as node:
            await asyncio.to_thread(_collect, rx, 3)
            node.faults.inject(FaultKind.SILENCE)
            await asyncio.sleep(0)  # let the send task see the fault before draining
            await asyncio.to_thread(_collect, rx, 1000, 0.05)  # drain frames already queued
            during = len(await asyncio.to_thread(_collect, rx, 1, 0.2))
            node.faults.clear(FaultKind.SILENCE)
            after = len(await asyncio.to_thread(_collect, rx, 3))
            return during, after

    during, after = asyncio.run(main())
    assert during == 0
    assert after == 3


def test_remote_hub_carries_the_node_frames_to_another_bus() -> None:
    channel = f"hub-{uuid.uuid4().hex}"
    hub = CanHub("ws://127.0.0.1:0/", channel=channel)
    hub.start()
    tx = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    client = can.Bus(interface="remote", channel=hub.url, ignore_config=True)
    try:

        async def main() -> list[can.Message]:
            async with SimulatedCanNode(TimelineSource(ramp_timeline()), bus=tx):
                return await asyncio.to_thread(_collect, client, 20)

        frames = asyncio.run(main())
    finally:
        client.shutdown()
        tx.shutdown()
        hub.stop()
    decoded = [decode_frame(m.arbitration_id, m.data) for m in frames]
    assert len(decoded) == 20
    assert [counter_gap(a.counter, b.counter) for a, b in itertools.pairwise(decoded)] == [0] * 19
    assert decoded[0].speed_rpm == pytest.approx(1000.0, abs=5.0)
