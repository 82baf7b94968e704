"""Simulated DAQ against a real pymodbus client on loopback: values, counter, read-only, faults."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers.registers import RegisterEntry, RegisterMap, decode, default_register_map, read_blocks
from drivers.sim.faults import FaultKind
from drivers.sim.modbus_server import SimulatedDaq
from drivers.sim.source import TimelineSource
from tests.sim.simhelpers import FakeClock, ramp_timeline, wait_for

Body = Callable[[SimulatedDaq, AsyncModbusTcpClient], Awaitable[None]]


@asynccontextmanager
async def _client(port: int, timeout: float = 1.0) -> AsyncIterator[AsyncModbusTcpClient]:
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=timeout, retries=0, reconnect_delay=0)
    await client.connect()
    try:
        yield client
    finally:
        client.close()


def _run(
    body: Body, *, clock: FakeClock | None = None, register_map: RegisterMap | None = None, **kw: Any
) -> None:
    async def main() -> None:
        source = TimelineSource(ramp_timeline(), speedup=10.0, clock=clock or FakeClock())
        async with (
            SimulatedDaq(source, port=0, register_map=register_map, **kw) as daq,
            _client(daq.port) as c,
        ):
            await body(daq, c)

    asyncio.run(main())


async def _read_all(client: AsyncModbusTcpClient, reg_map: RegisterMap) -> Any:
    blocks = []
    for start, count in read_blocks(reg_map):
        rr = await client.read_input_registers(start, count=count, device_id=reg_map.unit_id)
        assert not rr.isError(), rr
        blocks.append((start, rr.registers))
    return decode(reg_map, blocks)


def _float_map(word_order: str) -> RegisterMap:
    entries = [
        RegisterEntry(f"T{c:02d}", 2 * (c - 1), "float32", 1.0, word_order, "housing", c)
        for c in range(1, 33)
    ]  # type: ignore[arg-type]
    entries.append(RegisterEntry("amb", 64, "float32", 1.0, word_order, "ambient", None))  # type: ignore[arg-type]
    entries += [RegisterEntry(f"S{c:02d}", 99 + c, "uint16", 1.0, "big", "status", c) for c in range(1, 33)]
    return RegisterMap(tuple(entries), unit_id=3, n_channels=32)


def test_int16_map_round_trip_follows_the_timeline() -> None:
    clock = FakeClock()
    run = ramp_timeline()

    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        clock.advance(5.0)  # 50 sample periods of 0.1 s; sim time 10 x 5 s = 50 s: halfway up the ramp
        values = await _read_all(c, default_register_map())
        expected = 0.5 * (run.temps_c[0] + run.temps_c[1])
        np.testing.assert_allclose(values.temps_c, np.round(expected, 2), atol=0.005 + 1e-9)
        assert values.ambient_c == pytest.approx(22.0, abs=0.006)
        assert values.counter == 50
        assert not values.status.any()

    _run(body, clock=clock)


@pytest.mark.parametrize("word_order", ["big", "little"])
def test_float32_maps_round_trip(word_order: str) -> None:
    clock = FakeClock()
    reg_map = _float_map(word_order)

    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        clock.advance(2.0)
        values = await _read_all(c, reg_map)
        expected = daq.source.at(20.0).temps_c
        np.testing.assert_allclose(values.temps_c, expected.astype(np.float32), rtol=1e-7)

    _run(body, clock=clock, register_map=reg_map)


def test_counter_advances_with_the_clock_and_stops_when_frozen() -> None:
    clock = FakeClock()

    async def counter(c: AsyncModbusTcpClient) -> int:
        rr = await c.read_input_registers(200, count=2, device_id=1)
        return (rr.registers[0] << 16) | rr.registers[1]

    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        clock.advance(0.35)
        assert await counter(c) == 3
        daq.faults.inject(FaultKind.FREEZE)
        clock.advance(1.0)
        assert await counter(c) == 3
        daq.faults.clear(FaultKind.FREEZE)
        assert await counter(c) == 13

    _run(body, clock=clock)


def test_writes_are_rejected() -> None:
    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        rr = await c.write_register(0, 1234, device_id=1)
        assert rr.isError() and rr.exception_code == 2
        values = await _read_all(c, default_register_map())
        assert values.temps_c[0] == pytest.approx(20.0)

    _run(body)


def test_channel_faults_show_in_status_and_values() -> None:
    clock = FakeClock()

    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        reg_map = default_register_map()
        daq.faults.inject(FaultKind.OPEN_CIRCUIT, channels=(5,))
        daq.faults.inject(FaultKind.OUT_OF_RANGE, channels=(7,))
        daq.faults.inject(FaultKind.NAN, channels=(9,))
        stuck = daq.faults.inject(FaultKind.STUCK, channels=(3,))
        first = await _read_all(c, reg_map)
        clock.advance(5.0)
        later = await _read_all(c, reg_map)
        assert later.status[4] == 1 and later.status[6] == 2
        assert later.temps_c[6] == pytest.approx(327.0)
        assert math.isnan(later.temps_c[8])
        assert later.temps_c[2] == first.temps_c[2]  # stuck while the timeline moved on
        assert later.temps_c[3] > first.temps_c[3] + 1.0
        daq.faults.clear(stuck)
        recovered = await _read_all(c, reg_map)
        assert recovered.temps_c[2] > first.temps_c[2] + 1.0

    _run(body, clock=clock)


def test_exception_short_and_garbled_replies_are_seen_by_the_client() -> None:
    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        exc = daq.faults.inject(FaultKind.EXCEPTION, value=6)
        rr = await c.read_input_registers(0, count=33, device_id=1)
        assert rr.isError() and rr.exception_code == 6
        daq.faults.clear(exc)
        short = daq.faults.inject(FaultKind.SHORT, value=2)
        rr = await c.read_input_registers(0, count=33, device_id=1)
        assert len(rr.registers) == 31
        daq.faults.clear(short)
        daq.faults.inject(FaultKind.GARBLED)
        c.comm_params.timeout_connect = 0.3
        with pytest.raises(ModbusException):
            await c.read_input_registers(0, count=33, device_id=1)
        daq.faults.clear(FaultKind.GARBLED)

        async def good() -> bool:
            try:
                rr = await c.read_input_registers(0, count=33, device_id=1)
            except ModbusException:
                await c.connect()
                return False
            return len(rr.registers) == 33

        await wait_for(good)

    _run(body)


def test_hang_times_out_and_recovers() -> None:
    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        c.comm_params.timeout_connect = 0.3
        daq.faults.inject(FaultKind.HANG)
        with pytest.raises(ModbusException):
            await c.read_input_registers(0, count=33, device_id=1)
        daq.faults.clear(FaultKind.HANG)

        async def answered() -> bool:
            try:
                rr = await c.read_input_registers(200, count=2, device_id=1)
            except ModbusException:
                return False
            return not rr.isError()

        await wait_for(answered)

    _run(body)


def test_drop_refuses_connections_and_comes_back_on_the_same_port() -> None:
    async def body(daq: SimulatedDaq, c: AsyncModbusTcpClient) -> None:
        port = daq.port
        daq.faults.inject(FaultKind.DROP)

        async def down() -> bool:
            async with _client(port, timeout=0.3) as probe:
                return not probe.connected

        await wait_for(down)
        daq.faults.clear(FaultKind.DROP)

        async def up() -> bool:
            async with _client(port, timeout=0.3) as probe:
                if not probe.connected:
                    return False
                rr = await probe.read_input_registers(0, count=33, device_id=1)
                return not rr.isError()

        await wait_for(up)
        assert daq.port == port

    _run(body)
