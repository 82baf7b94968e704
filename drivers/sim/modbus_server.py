"""Simulated temperature DAQ: a pymodbus TCP server whose input registers follow a timeline.

The DAQ "samples" every ``sample_period_s`` wall seconds: sample ``k`` shows the timeline at simulated time
``times_s[0] + speedup * k * sample_period_s`` and the uint32 sample counter reads ``k`` (mod 2**32).
Registers are refreshed lazily when a request arrives (pymodbus device ``action`` hook), so there is no
background timer and an injected clock fully controls what a client reads. Values are encoded with
``drivers.registers.encode`` for any register map (every type, word order, scale/offset and "no value"
sentinel the map allows). The registers sit in the map's table: input registers (FC4) or holding registers
(FC3); a read of the other table gets an "illegal function" exception, a write "illegal data address".

Faults (``drivers.sim.faults``): channel faults change values/status; ``freeze`` stops sampling; ``hang``
holds replies back; ``drop`` closes every connection and the listening socket until cleared (the port is
kept); ``short``/``garbled`` rewrite the outgoing reply; ``exception`` answers with an exception response;
``wrong-fc``/``wrong-unit``/``wrong-tid`` rewrite the reply's function code, unit id or transaction id.
``counter_start`` offsets the sample counter (it wraps modulo 2**16 or 2**32 with its register type), so a
test can cross the wrap-around.

A poll of several register blocks sees one consistent sample: a request that starts at the map's lowest
address takes a new snapshot, and requests for higher addresses within ``latch_s`` wall seconds (default
50 ms) are answered from it, like a DAQ that latches its registers when the first block is read. Without
this a poll could pair the temperatures of one sample with the counter of the next.

Usage::

    async with SimulatedDaq(TimelineSource(run, speedup=60), port=0) as daq:
        print(daq.host, daq.port)

Errors: ``drivers.errors.DeviceUnavailableError`` when the port cannot be bound.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
from collections.abc import Sequence
from types import TracebackType
from typing import Literal

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.errors import DeviceUnavailableError, EncodeError
from drivers.registers import (
    RegisterMap,
    RegisterValues,
    default_register_map,
    encode,
    read_blocks,
    value_limits,
)
from drivers.sim.faults import FaultController, FaultKind, apply_channel_faults
from drivers.sim.source import TimelineSource

__all__ = ["SimulatedDaq"]

Sampling = Literal["clock", "row"]
_READ_CODES = (3, 4)
_SUPERVISE_S = 0.02


class SimulatedDaq:
    """A Modbus TCP DAQ on ``host:port`` (``port=0``: ephemeral, see :attr:`port` once started)."""

    def __init__(
        self,
        source: TimelineSource,
        *,
        host: str = "127.0.0.1",
        port: int = 5020,
        register_map: RegisterMap | None = None,
        faults: FaultController | None = None,
        sample_period_s: float = 0.1,
        sampling: Sampling = "clock",
        row_counters: Sequence[int] | None = None,
        latch_s: float = 0.05,
        counter_start: int = 0,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.register_map = register_map or default_register_map()
        self.faults = faults or FaultController(clock=source.clock)
        self.sample_period_s = sample_period_s
        self.sampling: Sampling = sampling
        self.row_counters = None if row_counters is None else list(row_counters)
        self.requests_served = 0
        self.counter_start = counter_start
        counters = self.register_map.role("counter")
        self._counter_modulus = counters[0].modulus if counters else 2**32
        self._server: ModbusTcpServer | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._cache_key: tuple[int, tuple[int, ...]] | None = None
        self.latch_s = latch_s
        self._lowest_address = self.register_map.entries[0].address
        self._latched_at = float("-inf")
        self._latched_signature: tuple[int, ...] = ()
        self._frozen_k: int | None = None
        self._last_k: int | None = None
        self._words: dict[int, int] = {}

    # ------------------------------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Bind and serve; the timeline and the fault schedule start now if they have not already."""
        self.source.wall_elapsed_s()
        self.faults.start()
        await self._listen()
        self._supervisor = asyncio.create_task(self._supervise(), name="sim-daq-supervisor")

    async def stop(self) -> None:
        """Close every connection and the listening socket."""
        if self._supervisor is not None:
            self._supervisor.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._supervisor
            self._supervisor = None
        await self._close_server()

    async def __aenter__(self) -> SimulatedDaq:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    @property
    def serving(self) -> bool:
        """True while the listening socket is open (False during a ``drop`` fault)."""
        return self._server is not None

    def _device(self) -> SimDevice:
        blocks = read_blocks(self.register_map, max_count=0x10000)
        simdata = [
            SimData(start, count=count, values=0, datatype=DataType.REGISTERS, readonly=True)
            for start, count in blocks
        ]
        return SimDevice(id=self.register_map.unit_id, simdata=simdata, action=self._action)

    async def _listen(self) -> None:
        server = ModbusTcpServer(
            self._device(), address=(self.host, self.port), trace_packet=self._trace_packet
        )
        try:
            await server.serve_forever(background=True)
        except (RuntimeError, OSError) as err:
            raise DeviceUnavailableError(
                f"cannot listen: {err}", device=f"sim-daq {self.host}:{self.port}"
            ) from err
        sockets = getattr(server.transport, "sockets", None) or []
        if sockets:
            self.port = int(sockets[0].getsockname()[1])
        self._server = server

    async def _close_server(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()

    async def _supervise(self) -> None:
        """Apply ``drop`` faults (close/reopen the socket) as they start and end."""
        while True:
            down = self.faults.is_active(FaultKind.DROP)
            if down and self._server is not None:
                await self._close_server()
            elif not down and self._server is None:
                with contextlib.suppress(DeviceUnavailableError):
                    await self._listen()
            await asyncio.sleep(_SUPERVISE_S)

    # ------------------------------------------------------------------------------------------- requests
    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if set_values is not None:
            return ExcCodes.ILLEGAL_ADDRESS
        if function_code != self.register_map.function_code:
            return ExcCodes.ILLEGAL_FUNCTION
        if self.faults.active():  # the common case, no fault at all, skips these checks
            while self.faults.is_active(FaultKind.HANG) or self.faults.is_active(FaultKind.DROP):
                await asyncio.sleep(0.005)
            exc = self.faults.first(FaultKind.EXCEPTION)
            if exc is not None:
                return ExcCodes(int(exc.param()))
        self._refresh(address)
        offset, words = address - start_address, self._words
        registers[offset : offset + count] = [words.get(a, 0) for a in range(address, address + count)]
        self.requests_served += 1
        return None

    def sample_index(self) -> int:
        """Index ``k`` of the DAQ sample shown now (while a ``freeze`` fault is on: the last one served).

        ``sampling="clock"``: one sample per ``sample_period_s`` wall seconds; ``"row"``: the timeline row
        at or before the current simulated time (replays: one device sample per recorded row).
        """
        if self.sampling == "row":
            k = self.source.at(self.source.sim_time_s()).index
        else:
            k = math.floor(self.source.wall_elapsed_s() / self.sample_period_s + 1e-9)
        if self.faults.is_active(FaultKind.FREEZE):
            if self._frozen_k is None:  # hold the last sample a client could have seen
                self._frozen_k = k if self._last_k is None else self._last_k
            return self._frozen_k
        self._frozen_k = None
        self._last_k = k
        return k

    def current_values(self) -> RegisterValues:
        """Engineering values the registers hold now (timeline sample plus channel faults)."""
        k = self.sample_index()
        times = self.source.run.times_s
        if self.sampling == "row":
            snap = self.source.at(float(times[k]))
        else:
            snap = self.source.at(float(times[0]) + self.source.speedup * k * self.sample_period_s)
        temps, status = apply_channel_faults(snap.temps_c, snap.status, self.faults)
        counter = k
        if self.row_counters is not None and self.sampling == "row" and self.row_counters[k] >= 0:
            counter = self.row_counters[k]
        return RegisterValues(
            temps_c=temps,
            ambient_c=snap.ambient_c,
            status=status,
            ambient_status=0,
            counter=(counter + self.counter_start) % self._counter_modulus,
        )

    def _refresh(self, address: int) -> None:
        """Take a new snapshot, unless this request continues a poll (see ``latch_s``)."""
        now = self.source.clock()
        signature = self.faults.signature()
        continues_poll = (
            address > self._lowest_address
            and now - self._latched_at <= self.latch_s
            and signature == self._latched_signature
        )
        if continues_poll:
            return
        self._latched_at, self._latched_signature = now, signature
        key = (self.sample_index(), signature)
        if key == self._cache_key:
            return
        self._words = _encode_clipped(self.register_map, self.current_values())
        self._cache_key = key

    # -------------------------------------------------------------------------------------- packet faults
    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        """Rewrite outgoing read replies for the ``short``, ``garbled`` and wrong-header faults."""
        if not sending or len(data) < 9 or data[7] not in _READ_CODES:
            return data
        data = self._rewrite_header(data)
        short = self.faults.first(FaultKind.SHORT)
        if short is not None:
            return _shorten(data, max(1, int(short.param())))
        garbled = self.faults.first(FaultKind.GARBLED)
        if garbled is not None:
            return _garble(data, int(garbled.value or 1))
        return data

    def _rewrite_header(self, data: bytes) -> bytes:
        """Apply ``wrong-fc``, ``wrong-unit`` and ``wrong-tid`` to an outgoing reply's MBAP header and FC."""
        tid, unit, fc = int.from_bytes(data[0:2], "big"), data[6], data[7]
        if (f := self.faults.first(FaultKind.WRONG_TID)) is not None:
            tid = (tid + int(f.param())) & 0xFFFF
        if (f := self.faults.first(FaultKind.WRONG_UNIT)) is not None:
            unit = int(f.param()) & 0xFF
        if (f := self.faults.first(FaultKind.WRONG_FC)) is not None:
            fc = int(f.param()) & 0xFF
        return tid.to_bytes(2, "big") + data[2:6] + bytes([unit, fc]) + data[8:]


def _shorten(packet: bytes, missing: int) -> bytes:
    """A consistent reply with ``missing`` registers fewer than the original (at least one kept)."""
    byte_count = packet[8]
    keep = max(2, byte_count - 2 * missing)
    pdu = packet[7:8] + bytes([keep]) + packet[9 : 9 + keep]
    return packet[:4] + struct.pack(">H", len(pdu) + 1) + packet[6:7] + pdu


def _garble(packet: bytes, mode: int) -> bytes:
    """Mode 1: the reply cut in the middle (the header announces the full length; the client waits for
    bytes that never come). Mode 2: the byte-count field claims 4 more bytes than are present."""
    if mode == 2:
        return packet[:8] + bytes([(packet[8] + 4) & 0xFF]) + packet[9:]
    return packet[: 9 + (len(packet) - 9) // 2]


def _encode_clipped(reg_map: RegisterMap, values: RegisterValues) -> dict[int, int]:
    """Encode; a temperature its register cannot hold is clipped to the register's range and flagged out of
    range (status 2), as a DAQ saturates."""
    try:
        return encode(reg_map, values)
    except EncodeError:
        temps = np.array(values.temps_c, dtype=float, copy=True)
        status = np.array(values.status, dtype=np.int64, copy=True)
        ambient = values.ambient_c
        for e in reg_map.entries:
            lo, hi = value_limits(e)
            if e.role in ("bearing", "housing"):
                i = (e.channel or 1) - 1
                if math.isfinite(temps[i]) and not lo <= temps[i] <= hi:
                    temps[i], status[i] = float(np.clip(temps[i], lo, hi)), 2
            elif e.role == "ambient" and math.isfinite(ambient):
                ambient = float(np.clip(ambient, lo, hi))
        clipped = RegisterValues(temps, ambient, status, values.ambient_status, values.counter)
        return encode(reg_map, clipped)
