"""Modbus DAQ driver against real servers on loopback (pymodbus, pyModbusTCP, a raw broken one)."""

from __future__ import annotations

import asyncio
import math
import struct
import time
from collections.abc import Awaitable, Callable

import numpy as np
import pytest
from pyModbusTCP.server import ModbusServer

from drivers.base import Backoff
from drivers.errors import (
    DeviceTimeoutError,
    DeviceUnavailableError,
    ModbusExceptionError,
    ShortReplyError,
)
from drivers.modbus_daq import ModbusDaq
from drivers.quality import Quality
from drivers.registers import RegisterEntry, RegisterMap, RegisterValues, default_register_map, encode

from .drvhelpers import FakeClock, PymodbusDaqServer, RawModbusServer, free_port, poll_until

MAP = default_register_map()


def _words(
    temps: np.ndarray, *, counter: int, status: np.ndarray | None = None, ambient: float = 21.0
) -> dict:
    st = np.zeros(32, dtype=np.int64) if status is None else status
    return encode(MAP, RegisterValues(temps, ambient, st, 0, counter))


def _with_server(body: Callable[[PymodbusDaqServer], Awaitable[None]], words: dict | None = None) -> None:
    async def main() -> None:
        server = await PymodbusDaqServer(free_port(), words or _words(np.full(32, 25.0), counter=1)).start()
        try:
            await body(server)
        finally:
            await server.stop()

    asyncio.run(main())


def test_reads_default_map_from_pymodbus_server_with_fc4_only() -> None:
    temps = np.round(np.linspace(-12.5, 95.25, 32), 2)
    status = np.zeros(32, dtype=np.int64)
    status[[3, 9]] = [1, 2]

    async def body(server: PymodbusDaqServer) -> None:
        async with ModbusDaq("127.0.0.1", server.port, timeout_s=0.5) as daq:
            r = await daq.read()
            np.testing.assert_allclose(r.temps_c, temps)
            assert r.ambient_c == pytest.approx(19.75) and r.counter == 70000
            assert r.t.tzinfo is not None and r.t.utcoffset().total_seconds() == 0
            assert r.quality[3] == Quality.OPEN_CIRCUIT and r.quality[9] == Quality.OUT_OF_RANGE
            assert int(np.sum(r.quality == Quality.OK)) == 30
            assert r.flags == {"ok": 30, "open_circuit": 1, "out_of_range": 1}
        assert set(server.function_codes) == {4}  # input registers only, never a write
        assert len(server.function_codes) == 3  # one request per merged block

    _with_server(body, _words(temps, counter=70000, status=status, ambient=19.75))


def test_pymodbustcp_server_float32_both_word_orders_and_negative_int16() -> None:
    entries = [
        RegisterEntry(f"F{c:02d}", 2 * (c - 1), "float32", 1.0, "big", "bearing", c) for c in range(1, 9)
    ]
    entries += [
        RegisterEntry(f"L{c:02d}", 2 * (c - 1), "float32", 1.0, "little", "housing", c) for c in range(9, 17)
    ]
    entries += [RegisterEntry(f"I{c:02d}", c + 15, "int16", 0.01, "big", "housing", c) for c in range(17, 33)]
    entries.append(RegisterEntry("amb", 60, "int16", 0.1, "big", "ambient", None))
    reg_map = RegisterMap(tuple(entries), n_channels=32)
    expected = np.concatenate([np.linspace(-20.5, 80.25, 16), np.linspace(-150.0, 300.0, 16)])
    words: dict[int, int] = {}
    for c in range(1, 17):  # word layout written here with struct, independently of drivers.registers
        hi, lo = struct.unpack(">HH", struct.pack(">f", expected[c - 1]))
        words[2 * (c - 1)] = hi if c <= 8 else lo
        words[2 * (c - 1) + 1] = lo if c <= 8 else hi
    for c in range(17, 33):
        words[c + 15] = struct.unpack(">H", struct.pack(">h", round(expected[c - 1] * 100)))[0]
    words[60] = struct.unpack(">H", struct.pack(">h", -55))[0]
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True)
    server.start()
    try:
        for addr, w in words.items():
            server.data_bank.set_input_registers(addr, [w])

        async def main() -> None:
            async with ModbusDaq("127.0.0.1", server.port, register_map=reg_map, timeout_s=0.5) as daq:
                r = await daq.read()
                np.testing.assert_allclose(r.temps_c, expected, rtol=1e-6)
                assert r.ambient_c == pytest.approx(-5.5)
                assert r.counter is None

        asyncio.run(main())
    finally:
        server.stop()


def test_exception_response_for_unmapped_address() -> None:
    entries = [e for e in MAP.entries if e.role != "counter"]
    entries.append(RegisterEntry("counter", 300, "uint32", 1.0, "big", "counter", None))
    reg_map = RegisterMap(tuple(entries))

    async def body(server: PymodbusDaqServer) -> None:
        async with ModbusDaq("127.0.0.1", server.port, register_map=reg_map, timeout_s=0.5) as daq:
            with pytest.raises(
                ModbusExceptionError, match=r"exception 2 \(illegal data address\).*300-301"
            ) as info:
                await daq.read()
            assert info.value.exception_code == 2
            assert daq.connected  # a clean exception response keeps the link
            assert daq.metrics.errors == {"ModbusExceptionError": 1}

    _with_server(body)


@pytest.mark.parametrize(
    ("mode", "pattern"),
    [
        ("short", r"registers 0-32: expected 33 registers, got 31"),
        ("truncated", "garbled reply"),
        ("garbage", "garbled reply, 15 bytes: de ad be ef"),
    ],
)
def test_short_and_garbled_replies(mode: str, pattern: str) -> None:
    async def main() -> None:
        server = await RawModbusServer(free_port(), mode=mode, short_by=2).start()
        try:
            async with ModbusDaq("127.0.0.1", server.port, timeout_s=0.3) as daq:
                with pytest.raises(ShortReplyError, match=pattern):
                    await daq.read()
                assert daq.metrics.errors == {"ShortReplyError": 1}
        finally:
            await server.stop()

    asyncio.run(main())


def test_hung_device_times_out_goes_stale_and_recovers() -> None:
    clock = FakeClock()

    async def body(server: PymodbusDaqServer) -> None:
        backoff = Backoff(initial_s=0.1, max_s=0.2, jitter=0.0)
        async with ModbusDaq(
            "127.0.0.1", server.port, timeout_s=0.2, stale_after_s=5.0, clock=clock, backoff=backoff
        ) as daq:
            assert (await daq.read()).quality.tolist() == [Quality.OK] * 32
            server.hang.set()
            with pytest.raises(DeviceTimeoutError, match="no reply for input registers 0-32"):
                await daq.read()
            assert not daq.connected
            with pytest.raises(DeviceUnavailableError, match="reconnect"):
                await daq.read()  # backoff not yet elapsed: fails fast without touching the device
            clock.advance(6.0)
            assert daq.is_stale()
            assert set(daq.current().quality.tolist()) == {Quality.STALE}
            server.hang.clear()
            server.words.update(_words(np.full(32, 26.0), counter=2))
            r = await daq.read()
            assert r.temps_c[0] == pytest.approx(26.0) and set(r.quality.tolist()) == {Quality.OK}
            assert not daq.is_stale() and daq.metrics.reconnects == 1
            assert daq.metrics.events["polls_while_down"] == 1

    _with_server(body)


def test_restart_detected_and_reconnect_after_outage_within_backoff_cap() -> None:
    async def main() -> None:
        port = free_port()
        server = await PymodbusDaqServer(port, _words(np.full(32, 30.0), counter=500)).start()
        daq = ModbusDaq("127.0.0.1", port, timeout_s=0.2)  # default backoff, capped at 2 s
        readings = []
        task = asyncio.create_task(daq.run(interval_s=0.05, on_reading=readings.append))
        try:
            await poll_until(lambda: len(readings) >= 2)
            await server.stop()
            await poll_until(lambda: daq.metrics.connect_failures >= 4, timeout_s=10)  # backoff has grown
            server = await PymodbusDaqServer(port, _words(np.full(32, 30.0), counter=3)).start()
            back_at, n_before = time.monotonic(), len(readings)
            await poll_until(lambda: len(readings) > n_before, timeout_s=5)
            assert time.monotonic() - back_at <= daq.backoff.max_s + 0.05 + 0.5
            assert readings[-1].restarted and daq.metrics.events["restarts"] == 1
            assert daq.metrics.reconnects == 1
            assert (
                daq.metrics.errors.get("DeviceUnavailableError", 0)
                + daq.metrics.errors.get("DeviceTimeoutError", 0)
                >= 4
            )
        finally:
            task.cancel()
            await daq.close()
            await server.stop()

    asyncio.run(main())


def test_quality_nan_range_stuck_and_frozen_counter() -> None:
    clock = FakeClock()
    temps = np.full(32, 40.0)
    temps[0] = math.nan
    temps[1] = 300.0  # beyond the plausible range

    async def body(server: PymodbusDaqServer) -> None:
        async with ModbusDaq(
            "127.0.0.1", server.port, timeout_s=0.5, stale_after_s=30.0, stuck_samples=3, clock=clock
        ) as daq:
            for k in range(3):  # channel 5 (index 4) repeats exactly, the others drift
                t = temps + 0.37 * k
                t[4] = 55.55
                server.words.update(_words(t, counter=10 + k))
                r = await daq.read()
                clock.advance(10.0)
            assert r.quality[0] == Quality.NAN and math.isnan(r.temps_c[0])
            assert r.quality[1] == Quality.OUT_OF_RANGE
            assert r.quality[4] == Quality.STUCK
            assert int(np.sum(r.quality == Quality.OK)) == 29
            # same counter on later polls: not a new sample; frozen for > 30 s → all STALE
            r = await daq.read()
            assert not r.new_sample and r.quality[2] == Quality.OK
            clock.advance(31.0)
            r = await daq.read()
            assert set(r.quality.tolist()) == {Quality.STALE} and r.ambient_quality is Quality.STALE
            assert daq.is_stale()

    _with_server(body)


def test_injected_client_gets_the_same_translation() -> None:
    class DeadClient:
        connected = False

        async def connect(self) -> bool:
            return False

        def close(self) -> None:
            pass

        def read_input_registers(self, address: int, *, count: int = 1, device_id: int = 1) -> object:
            raise AssertionError("not connected, must not be called")

    async def main() -> None:
        async with ModbusDaq("device.invalid", 502, client=DeadClient(), timeout_s=0.1) as daq:
            with pytest.raises(DeviceUnavailableError, match=r"device\.invalid:502: cannot connect"):
                await daq.read()
            assert daq.metrics.connect_failures == 1

    asyncio.run(main())


def test_driver_can_be_built_outside_the_event_loop() -> None:
    words = _words(np.full(32, 33.3), counter=9)
    daq = ModbusDaq("127.0.0.1", free_port(), timeout_s=0.5)  # no running loop here: nothing is opened yet

    async def main() -> None:
        server = await PymodbusDaqServer(daq.port, words).start()
        try:
            async with daq:
                assert (await daq.read()).counter == 9
        finally:
            await server.stop()

    asyncio.run(main())
