"""Async Modbus TCP driver for the 32-channel temperature DAQ (reads input (FC4) or holding (FC3) registers,
as the register map's ``table`` says; never writes).

Uses pymodbus' ``AsyncModbusTcpClient`` with its own retries and automatic reconnect switched off
(``retries=0, reconnect_delay=0``; pymodbus' backoff grows to 300 s): reconnecting is ``Source``'s bounded
backoff. The unit id is ``unit_id`` when given (setting ``modbus.unit``), else the register map's ``unit_id``
(``self.unit_id`` is the one in use). pymodbus errors are translated here, once:

- ``ExceptionResponse`` / ``isError()``         → ``ModbusExceptionError`` (with the exception code)
- fewer registers than asked                   → ``ShortReplyError`` naming the register range
- a reply whose transaction id, unit id or function code is not the request's → ``ReplyMismatchError``
  naming the field, the expected and the received value
- a reply whose byte count disagrees with its length, or bytes that are no frame → ``ShortReplyError``
  ("garbled reply", with the bytes)
- nothing arrived in time                      → ``DeviceTimeoutError`` (link dropped, reconnect)
- connection refused / lost                    → ``DeviceUnavailableError`` (reconnect with backoff)

Every received frame is checked in pymodbus' ``trace_packet`` hook, before pymodbus decodes it: a bad one is
withheld from pymodbus (which would otherwise skip it and time out, or raise inside the event loop's
``data_received`` and log an asyncio traceback) and fails the pending request at once with the named error
(through ``TransactionManager.response_future``; should a pymodbus version lack it, the request times out
and the same named error is raised). The link is then re-established, since the byte stream may be out of
step.

Each good poll gives a ``DaqReading`` whose per-channel ``quality`` says: DAQ status 1 → ``OPEN_CIRCUIT``,
2 → ``OUT_OF_RANGE`` (also outside ``valid_range_c``), NaN → ``NAN``, identical value over
``stuck_samples`` device samples → ``STUCK``, device sample counter frozen for ``stale_after_s`` → ``STALE``.
The counter is compared modulo its register width (2**32 for uint32): an advance by less than half the range
is a new sample (so 0xFFFFFFFF → 0 is one), a step back is a device restart (counted; stuck history reset).
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from drivers.base import Source, StuckDetector
from drivers.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeoutError,
    DeviceUnavailableError,
    ModbusExceptionError,
    ProtocolError,
    ReplyMismatchError,
    ShortReplyError,
)
from drivers.quality import PRECEDENCE, Quality, from_daq_status
from drivers.registers import RegisterMap, RegisterValues, decode, default_register_map, read_blocks

FC_READ_INPUT_REGISTERS = 4
FC_READ_HOLDING_REGISTERS = 3
_MBAP = struct.Struct(">HHHBB")  # transaction id, protocol id, length, unit id, function code
_RANK = np.array([PRECEDENCE.index(q) for q in sorted(Quality)])  # lower rank wins


class ModbusClient(Protocol):
    """What the driver needs from a pymodbus async client (``client=`` may be any object like this)."""

    @property
    def connected(self) -> bool: ...

    async def connect(self) -> bool: ...

    def close(self) -> None: ...

    def read_input_registers(self, address: int, *, count: int = 1, device_id: int = 1) -> Any: ...

    def read_holding_registers(self, address: int, *, count: int = 1, device_id: int = 1) -> Any: ...


@dataclass(frozen=True)
class DaqReading:
    """One DAQ poll.

    ``t`` UTC; temps_c (n,) °C; ambient_c °C; status (n,) DAQ codes; counter (device sample count, ``None``
    if unmapped); quality (n,) ``Quality`` as uint8; ``new_sample`` when the device counter advanced since
    the previous poll; ``restarted`` when it went backwards.
    """

    t: datetime
    temps_c: npt.NDArray[np.float64]
    ambient_c: float
    status: npt.NDArray[np.int64]
    counter: int | None
    quality: npt.NDArray[np.uint8]
    ambient_quality: Quality = Quality.OK
    new_sample: bool = True
    restarted: bool = False
    flags: dict[str, int] = field(default_factory=dict)  # count per Quality label, for logs and health


class ModbusDaq(Source[DaqReading]):
    """The temperature DAQ over Modbus TCP: ``async with ModbusDaq(host, port) as daq: await daq.read()``.

    ``timeout_s`` is per Modbus request (s); ``stale_after_s`` how long the device sample counter may stay
    unchanged (s); ``stuck_samples`` identical device samples before a channel is ``STUCK`` (``None``: off);
    ``valid_range_c`` plausible temperatures (°C). ``unit_id`` (0–247) overrides the map's ``unit_id``.
    ``client=`` injects a pymodbus-like async client.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 502,
        *,
        register_map: RegisterMap | None = None,
        timeout_s: float = 1.0,
        stale_after_s: float = 30.0,
        stuck_samples: int | None = 60,
        stuck_tolerance_c: float = 0.0,
        valid_range_c: tuple[float, float] = (-40.0, 250.0),
        unit_id: int | None = None,
        client: ModbusClient | None = None,
        **source_kwargs: Any,
    ) -> None:
        super().__init__(
            name=f"modbus {host}:{port}", timeout_s=timeout_s, stale_after_s=stale_after_s, **source_kwargs
        )
        self.host, self.port = host, port
        self.register_map = register_map or default_register_map()
        self.unit_id = self.register_map.unit_id if unit_id is None else unit_id
        if not 0 <= self.unit_id <= 247:
            raise ConfigError(f"unit id {self.unit_id} outside 0..247", entry="modbus.unit")
        self.function_code = self.register_map.function_code
        counters = self.register_map.role("counter")
        self._counter_modulus = counters[0].modulus if counters else 2**32
        self._sent: tuple[int, int, int] | None = None  # (transaction id, unit id, FC) of the last request
        self._reply_error: ProtocolError | None = None
        self._request_span = (0, 0)
        self.blocks: list[tuple[int, int]] = read_blocks(self.register_map)
        self.valid_range_c = valid_range_c
        self._rx: list[bytes] = []
        self._client: ModbusClient | None = client  # built on first connect (pymodbus needs a running loop)
        n = self.register_map.n_channels
        self._stuck = (
            StuckDetector(n, samples=stuck_samples, tolerance=stuck_tolerance_c) if stuck_samples else None
        )
        self._stuck_mask = np.zeros(n, dtype=bool)
        self._last_counter: int | None = None
        self._counter_changed_at = float("-inf")

    def _make_client(self) -> ModbusClient:
        return AsyncModbusTcpClient(
            self.host,
            port=self.port,
            timeout=self.timeout_s,
            retries=0,
            reconnect_delay=0,
            name=self.name,
            trace_packet=self._trace_packet,
        )

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending:
            if len(data) >= _MBAP.size:
                tid, _pid, _len, unit, fc = _MBAP.unpack_from(data)
                self._sent, self._reply_error = (tid, unit, fc), None
            return data
        self._rx.append(bytes(data))
        problem = self._frame_problem(data)
        if problem is None:
            return data
        self._fail_pending(problem)
        return b""  # withheld: pymodbus neither skips it silently nor raises inside the event loop

    def _frame_problem(self, data: bytes) -> ProtocolError | None:
        """What is wrong with a received frame (``None``: fine, or not complete yet)."""
        if self._sent is None or len(data) < _MBAP.size:
            return None
        tid, pid, length, unit, fc = _MBAP.unpack_from(data)
        if pid != 0 or length < 3:
            return self._garbled(data, f"MBAP protocol id {pid}, length {length}")
        start, count = self._request_span
        for what, expected, got in (
            ("transaction id", self._sent[0], tid),
            ("unit id", self._sent[1], unit),
            ("function code", self._sent[2], fc & 0x7F),
        ):
            if got != expected:
                return ReplyMismatchError(
                    field=what, expected=expected, got=got, start=start, count=count, device=self.name
                )
        if len(data) < 6 + length:
            return None  # more bytes to come (pymodbus times out if they never do)
        if fc & 0x80:
            return None if length == 3 else self._garbled(data, f"exception reply of length {length}")
        if data[8] != length - 3:
            return self._garbled(data, f"byte count {data[8]} but {length - 3} data bytes")
        return None

    def _garbled(self, data: bytes, why: str) -> ShortReplyError:
        start, count = self._request_span
        detail = f"garbled reply, {len(data)} bytes: {data[:16].hex(' ')} ({why})"
        return ShortReplyError(start=start, count=count, got=0, device=self.name, detail=detail)

    def _fail_pending(self, err: ProtocolError) -> None:
        """Remember ``err`` and fail the request pymodbus is waiting on (if it exposes the future)."""
        self._reply_error = err
        future = getattr(getattr(self._client, "ctx", None), "response_future", None)
        if isinstance(future, asyncio.Future) and not future.done():
            future.set_exception(err)

    # ---------------------------------------------------------------------------------------- Source hooks
    def _read_timeout_s(self) -> float:
        return self.timeout_s * (len(self.blocks) + 1)

    async def _connect(self) -> None:
        try:
            if self._client is None:
                self._client = self._make_client()
            ok = await self._client.connect()
        except (ModbusException, OSError) as err:
            raise DeviceUnavailableError(f"cannot connect: {err}", device=self.name) from err
        if not ok:
            raise DeviceUnavailableError("cannot connect (refused or unreachable)", device=self.name)

    async def _disconnect(self) -> None:
        if self._client is not None:
            self._client.close()

    def _needs_reconnect(self, err: DeviceError) -> bool:
        # A garbled reply may leave the byte stream out of step: start a fresh connection.
        garbled = isinstance(err, ShortReplyError) and err.got == 0
        return super()._needs_reconnect(err) or garbled or isinstance(err, ReplyMismatchError)

    async def _read_internal(self) -> DaqReading:
        blocks = [(start, await self._read_block(start, count)) for start, count in self.blocks]
        return self._assess(decode(self.register_map, blocks))

    # ---------------------------------------------------------------------------------------- protocol
    def _connected_client(self) -> ModbusClient:
        if self._client is None:
            raise DeviceUnavailableError("not connected", device=self.name)
        return self._client

    async def _read_block(self, start: int, count: int) -> list[int]:
        """Read ``count`` registers from ``start`` (FC4 or FC3), translating every pymodbus failure."""
        self._rx.clear()
        self._request_span, self._reply_error = (start, count), None
        client = self._connected_client()
        read = (
            client.read_input_registers
            if self.function_code == FC_READ_INPUT_REGISTERS
            else client.read_holding_registers
        )
        try:
            reply = await read(start, count=count, device_id=self.unit_id)
        except ModbusIOException as err:
            raise self._io_error(start, count) from err
        except ConnectionException as err:
            msg = f"connection lost reading {self._describe(start, count)}"
            raise DeviceUnavailableError(msg, device=self.name) from err
        except ModbusException as err:
            raise ProtocolError(
                f"bad reply for {self._describe(start, count)}: {err}", device=self.name
            ) from err
        except OSError as err:
            msg = f"socket error reading {self._describe(start, count)}: {err}"
            raise DeviceUnavailableError(msg, device=self.name) from err
        return self._check_reply(reply, start, count)

    def _io_error(self, start: int, count: int) -> Exception:
        if self._reply_error is not None:
            return self._reply_error
        received = b"".join(self._rx)
        if not self._connected_client().connected:
            return DeviceUnavailableError(
                f"connection lost reading {self._describe(start, count)}", device=self.name
            )
        if received:
            detail = f"garbled reply, {len(received)} bytes: {received[:32].hex(' ')}"
            return ShortReplyError(start=start, count=count, got=0, device=self.name, detail=detail)
        msg = f"no reply for {self._describe(start, count)} within {self.timeout_s:g} s"
        return DeviceTimeoutError(msg, device=self.name)

    def _check_reply(self, reply: Any, start: int, count: int) -> list[int]:
        if reply.isError():
            code = int(getattr(reply, "exception_code", 0))
            raise ModbusExceptionError(
                function_code=self.function_code,
                exception_code=code,
                start=start,
                count=count,
                device=self.name,
            )
        self._check_header(reply, start, count)
        registers: Sequence[int] = getattr(reply, "registers", None) or []
        if len(registers) != count:
            raise ShortReplyError(start=start, count=count, got=len(registers), device=self.name)
        return [int(w) & 0xFFFF for w in registers]

    def _describe(self, start: int, count: int) -> str:
        table = "input" if self.function_code == FC_READ_INPUT_REGISTERS else "holding"
        return f"{table} registers {start}-{start + count - 1}"

    def _check_header(self, reply: Any, start: int, count: int) -> None:
        """The decoded reply's function code and unit id (also for an injected client without the hook)."""
        fc = getattr(reply, "function_code", self.function_code)
        unit = getattr(reply, "dev_id", self.unit_id)
        for what, expected, got in (
            ("function code", self.function_code, fc),
            ("unit id", self.unit_id, unit),
        ):
            if isinstance(got, int) and got != expected and not (what == "unit id" and expected == 0):
                raise ReplyMismatchError(
                    field=what, expected=expected, got=got, start=start, count=count, device=self.name
                )

    # ---------------------------------------------------------------------------------------- quality
    def is_stale(self) -> bool:
        """True when no good poll for ``stale_after_s`` or the device sample counter is frozen that long."""
        return super().is_stale() or self._clock() - self._counter_changed_at > self.stale_after_s

    def current(self) -> DaqReading:
        """The latest reading, every channel ``STALE`` if the device has been silent or frozen for
        ``stale_after_s``. Raises ``NoDataError`` before the first good poll."""
        latest = self.latest()
        if not self.is_stale():
            return latest
        stale = np.full_like(latest.quality, np.uint8(Quality.STALE))
        return replace(latest, quality=stale, ambient_quality=Quality.STALE, flags={"stale": len(stale)})

    def _track_counter(self, counter: int | None) -> tuple[bool, bool]:
        """(new_sample, restarted) from the device sample counter."""
        now = self._clock()
        previous, self._last_counter = self._last_counter, counter
        if counter is None or previous is None or counter != previous:
            self._counter_changed_at = now
        if counter is None or previous is None:
            return True, False
        restarted = (counter - previous) % self._counter_modulus >= self._counter_modulus // 2
        if restarted:
            self.metrics.count("restarts")
            if self._stuck is not None:
                self._stuck.reset()
        return counter != previous, restarted

    def _assess(self, v: RegisterValues) -> DaqReading:
        new_sample, restarted = self._track_counter(v.counter)
        if new_sample:
            self.metrics.count("new_samples")
            if self._stuck is not None:
                self._stuck_mask = self._stuck.update(v.temps_c)
        stale = self._clock() - self._counter_changed_at > self.stale_after_s
        if stale:
            self.metrics.count("stale_polls")
        quality = channel_quality(
            v.temps_c, v.status, stuck=self._stuck_mask, stale=stale, valid_range_c=self.valid_range_c
        )
        amb = channel_quality(
            np.array([v.ambient_c]),
            np.array([v.ambient_status]),
            stale=stale,
            valid_range_c=self.valid_range_c,
        )
        return DaqReading(
            t=self._now(),
            temps_c=v.temps_c,
            ambient_c=v.ambient_c,
            status=v.status,
            counter=v.counter,
            quality=quality,
            ambient_quality=Quality(int(amb[0])),
            new_sample=new_sample,
            restarted=restarted,
            flags=quality_counts(quality),
        )


def channel_quality(
    temps_c: npt.NDArray[np.float64],
    status: npt.NDArray[np.int64],
    *,
    stuck: npt.NDArray[np.bool_] | None = None,
    stale: bool = False,
    valid_range_c: tuple[float, float] = (-40.0, 250.0),
) -> npt.NDArray[np.uint8]:
    """Per-channel ``Quality`` (uint8) from values (°C), DAQ status codes, a stuck mask and staleness.

    Where several conditions hold, the first in ``quality.PRECEDENCE`` wins.
    """
    lo, hi = valid_range_c
    nan = np.isnan(temps_c)
    with np.errstate(invalid="ignore"):
        out_of_range = ~nan & ((temps_c < lo) | (temps_c > hi))
    masks = {
        Quality.STALE: np.full(temps_c.shape, stale),
        Quality.NAN: nan,
        Quality.OUT_OF_RANGE: out_of_range,
        Quality.STUCK: np.zeros(temps_c.shape, bool) if stuck is None else stuck,
    }
    q = from_daq_status(status)
    for flag, mask in masks.items():
        q = np.where(mask & (_RANK[flag] < _RANK[q]), np.uint8(flag), q).astype(np.uint8)
    return q


def quality_counts(quality: npt.NDArray[np.uint8]) -> dict[str, int]:
    """Number of channels per flag label, e.g. ``{"ok": 30, "open_circuit": 2}``."""
    counts = np.bincount(quality, minlength=len(Quality))
    return {Quality(v).label: int(n) for v, n in enumerate(counts) if n}
