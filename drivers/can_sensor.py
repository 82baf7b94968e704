"""CAN driver for the spindle speed/torque sensor, on any python-can interface. Listens only, never sends.

The bus is created at the edge (``can.Bus(interface=..., channel=..., ignore_config=True, **options)`` in
``_connect``) or injected with ``bus=``. ``interface`` is any name python-can knows
(``can.interfaces.VALID_INTERFACES``: socketcan, pcan, kvaser, vector, ixxat, slcan, socketcand, remote,
virtual, …; anything else is a ``ConfigError`` naming ``can.interface``); ``bitrate``, ``fd``,
``data_bitrate``, ``can_filters`` and any further ``bus_kwargs`` go to the interface unchanged. A reader
thread hands frames to the event loop; ``read()`` returns the next decoded ``SpindleStatus`` frame. Every
problem is counted in ``metrics`` and named:

- unknown ID, extended (29-bit) ID, CAN FD, remote or error frame, wrong DLC, undecodable payload →
  ``read()`` raises the ``FrameError`` subclass (counted); the contract is CAN 2.0A;
- rolling-counter gap or repeat → the reading carries ``frames_lost`` and a ``CounterGapError`` is noted.
  A rejected ``SpindleStatus`` frame (bad status byte, wrong DLC) arrived, so it is not lost: its counter
  is taken when the payload holds it, and otherwise it is subtracted from the next gap;
- status byte 1 (warning) / 2 (fault) → counted; a fault makes the reading's quality ``FAULT``, and either
  makes ``condition()`` name it (the service then shows the device ``degraded`` with that reason);
- no ``SpindleStatus`` frame for ``stale_after_s`` → ``read()`` raises ``DeviceTimeoutError`` and
  ``current()`` reports ``STALE``;
- bus errors (interface down, remote server gone) and a bus that cannot be opened (device unplugged, vendor
  library missing, an option the interface rejects) → ``DeviceUnavailableError`` naming the cause, reconnect
  with backoff (so the acquisition keeps running and ``/healthz`` shows ``can`` down with the reason).

python-can errors are translated here, once.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Any

import can

from drivers.base import Source
from drivers.can_codec import (
    SPINDLE_STATUS_ID,
    SensorStatus,
    counter_gap,
    decode_frame,
    frame_counter,
    load_dbc,
)
from drivers.errors import (
    ConfigError,
    CounterGapError,
    DeviceError,
    DeviceUnavailableError,
    FrameError,
)
from drivers.quality import Quality

INBOX_SIZE = 10_000  # frames buffered between the reader thread and the event loop (100 s at 100 Hz)
BATCH_S = 0.0  # s; > 0 lets the reader thread group frames per wake-up (the service's setting: can.batch_s)


@dataclass(frozen=True)
class CanReading:
    """One ``SpindleStatus`` frame as received. ``t`` UTC receive time; speed rpm; torque N·m;
    ``quality`` OK, or FAULT when the sensor reports a fault (``current()`` adds STALE on silence);
    ``frames_lost`` frames missing before this one according to the rolling counter."""

    t: datetime
    speed_rpm: float
    torque_nm: float
    status: SensorStatus
    counter: int
    quality: Quality = Quality.OK
    frames_lost: int = 0


class _BusReader:
    """A daemon thread that blocks in ``bus.recv`` and hands frames (or the error that ended it) to the loop.

    A plain thread instead of ``can.Notifier``: the Notifier's file-descriptor mode swallows receive errors
    in the event loop's exception handler (and keeps firing on a dead socket), and its thread mode keeps
    calling ``recv`` after an error. Here the first error ends the thread and reaches ``read()``.

    Frames go into a bounded deque; the loop is woken once per batch, and only if no wake-up is pending.
    With ``batch_s`` > 0 the thread, woken by a batch's first frame, sleeps ``batch_s`` and then takes every
    frame that arrived meanwhile (``recv(0)`` until none is left): at 100 frames/s and 50 ms that is 20
    wake-ups/s of this thread and of the loop instead of 100 each (docs/design/threading.md, "CPU at real
    rate"); a frame reaches ``read()`` at most about ``batch_s`` late (the acquisition does not need
    better: samples are 10 s apart, silence is judged over 0.5 s). The default is 0 (each frame handed
    over at once) because callers that react frame by frame expect it.
    """

    def __init__(
        self,
        bus: can.BusABC,
        loop: asyncio.AbstractEventLoop,
        *,
        maxsize: int = INBOX_SIZE,
        batch_s: float = BATCH_S,
        poll_s: float = 0.1,
    ) -> None:
        self._batch_s = batch_s
        self.dropped = 0
        self.maxsize = maxsize
        self._bus, self._loop, self._poll_s = bus, loop, poll_s
        self._buf: deque[can.Message | BaseException] = deque()
        self._lock = threading.Lock()
        self._wake_pending = False
        self._ready = asyncio.Event()
        self._stop = threading.Event()
        # in a copy of the starter's context: a log line from this thread (python-can's) names its spindle
        ctx = contextvars.copy_context()
        self._thread = threading.Thread(
            target=ctx.run, args=(self._run,), name=f"can-reader {bus.channel_info}", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        """Ask the thread to end and wait up to ``timeout_s`` (it wakes every ``poll_s``)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def has_items(self) -> bool:
        """True when a frame (or error) is waiting."""
        return bool(self._buf)

    async def get(self) -> can.Message | BaseException:
        """The next frame or the error that ended the reader; waits as long as needed."""
        while True:
            if self._buf:
                return self._buf.popleft()
            self._ready.clear()
            if self._buf:  # arrived between the check and the clear
                return self._buf.popleft()
            await self._ready.wait()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                received = self._receive()
            except Exception as exc:  # any interface's failure (CanError, OSError, websocket, ...) ends it
                self._store(exc)
                self._wake_loop()
                return
            if received:
                self._wake_loop()

    def _receive(self) -> bool:
        """Wait up to ``poll_s`` for a frame and store it; with batching, then let ``batch_s`` pass and store
        every frame that arrived meanwhile (one wake-up of this thread per batch). False: nothing came."""
        msg = self._bus.recv(self._poll_s)
        if msg is None:
            return False
        self._store(msg)
        if self._batch_s > 0:
            self._stop.wait(self._batch_s)
            while (msg := self._bus.recv(0.0)) is not None:
                self._store(msg)
        return True

    def _store(self, item: can.Message | BaseException) -> None:
        with self._lock:
            if len(self._buf) >= self.maxsize and not isinstance(item, BaseException):
                self.dropped += 1
                return
            self._buf.append(item)

    def _wake_loop(self) -> None:
        with self._lock:
            if self._wake_pending:
                return
            self._wake_pending = True
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody is listening any more
            self._loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        with self._lock:
            self._wake_pending = False
        self._ready.set()


class CanSpindleSensor(Source[CanReading]):
    """Receives ``SpindleStatus`` frames. ``stale_after_s`` (s) of silence marks speed/torque stale.

    Either ``bus=`` (an open ``can.BusABC``, not closed by this driver) or ``interface``/``channel``
    (+ ``bitrate``, ``fd``, ``data_bitrate`` in bit/s, ``can_filters`` as python-can's list of
    ``{"can_id", "can_mask", "extended"}``, and ``bus_kwargs`` for anything else the interface takes) to
    create one per connection with ``bus_factory`` (default ``can.Bus``). ``dbc`` is a path (``None``:
    packaged DBC).
    ``inbox_size`` frames are buffered between the reader thread and the loop; beyond that frames are
    dropped and counted (``events["frames_dropped"]``). ``batch_s`` (s) groups frames per loop wake-up.
    """

    read_what = "SpindleStatus frame"

    def __init__(
        self,
        *,
        interface: str = "virtual",
        channel: str = "chtc",
        bitrate: int | None = None,
        fd: bool = False,
        data_bitrate: int | None = None,
        can_filters: Sequence[dict[str, Any]] | None = None,
        dbc: str | Path | None = None,
        stale_after_s: float = 0.5,
        bus: can.BusABC | None = None,
        bus_kwargs: dict[str, Any] | None = None,
        bus_factory: Callable[..., can.BusABC] = can.Bus,
        inbox_size: int = INBOX_SIZE,
        batch_s: float = BATCH_S,
        **source_kwargs: Any,
    ) -> None:
        name = "can injected bus" if bus is not None else f"can {interface}:{channel}"
        super().__init__(name=name, timeout_s=stale_after_s, stale_after_s=stale_after_s, **source_kwargs)
        if bus is None and interface not in can.interfaces.VALID_INTERFACES:
            known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            raise ConfigError(
                f"unknown python-can interface {interface!r} (one of {known})", entry="can.interface"
            )
        self.interface, self.channel, self.bitrate = interface, channel, bitrate
        self._db = load_dbc(dbc)
        self._injected = bus
        self._bus_factory = bus_factory
        self._bus_kwargs = dict(bus_kwargs or {})
        if fd:
            self._bus_kwargs["fd"] = True
        if data_bitrate is not None:
            self._bus_kwargs["data_bitrate"] = data_bitrate
        if can_filters is not None:
            self._bus_kwargs["can_filters"] = [dict(f) for f in can_filters]
        self._unread = 0  # rejected SpindleStatus frames whose counter could not be read
        self._bus: can.BusABC | None = None
        self._reader: _BusReader | None = None
        self._inbox_size, self._batch_s = inbox_size, batch_s
        self._dropped_seen = 0
        self._last_counter: int | None = None

    # ---------------------------------------------------------------------------------------- Source hooks
    def _needs_reconnect(self, err: DeviceError) -> bool:
        return isinstance(err, DeviceUnavailableError)  # silence is not a broken bus

    def _read_ready(self) -> bool:
        return self._reader is not None and self._reader.has_items()

    async def _connect(self) -> None:
        self._bus = self._injected or self._open_bus()
        self._reader = _BusReader(
            self._bus, asyncio.get_running_loop(), maxsize=self._inbox_size, batch_s=self._batch_s
        )
        self._dropped_seen = 0
        self._reader.start()
        self._last_counter = None

    def _open_bus(self) -> can.BusABC:
        kwargs = dict(self._bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            return self._bus_factory(
                interface=self.interface, channel=self.channel, ignore_config=True, **kwargs
            )
        except Exception as err:  # vendor back-ends fail in many ways (OSError, NameError, TypeError, ...)
            hint = ""
            if isinstance(err, NotImplementedError | ImportError | NameError | AttributeError | TypeError):
                hint = " (the interface is not usable here: vendor library missing, or an option it rejects)"
            msg = f"cannot open bus: {type(err).__name__}: {err}{hint}"
            raise DeviceUnavailableError(msg, device=self.name) from err

    async def _disconnect(self) -> None:
        reader, bus = self._reader, self._bus
        self._reader, self._bus = None, None
        if reader is not None:
            await asyncio.to_thread(reader.stop, 1.0)
        if bus is not None and bus is not self._injected:
            try:
                bus.shutdown()
            except (
                Exception
            ) as err:  # any interface's failure (e.g. a closed websocket): the bus is gone anyway
                self.note_error(DeviceUnavailableError(f"shutdown failed: {err}", device=self.name))

    async def _read_internal(self) -> CanReading:
        if self._reader is None:
            raise DeviceUnavailableError("not listening", device=self.name)
        item = await self._reader.get()
        if self._reader.dropped > self._dropped_seen:  # the loop fell behind and the inbox overflowed
            self.metrics.count("frames_dropped", self._reader.dropped - self._dropped_seen)
            self._dropped_seen = self._reader.dropped
        if isinstance(item, BaseException):
            raise DeviceUnavailableError(f"bus error: {item}", device=self.name) from item
        return self._process(item)

    async def read(self) -> CanReading:
        """The next ``SpindleStatus`` frame (waits at most ``stale_after_s``; see module docstring)."""
        try:
            return await super().read()
        except DeviceError as err:
            if not isinstance(err, FrameError):
                self._last_counter = None  # after silence/outage the counter restarts the comparison
            raise

    # ---------------------------------------------------------------------------------------- decoding
    def _process(self, msg: can.Message) -> CanReading:
        self.metrics.count("frames")
        kind = (
            "error" if msg.is_error_frame else "remote" if msg.is_remote_frame else "fd" if msg.is_fd else ""
        )
        if kind:
            self.metrics.count(f"{kind}_frames")
            what = "CAN FD frame (the contract is CAN 2.0A)" if kind == "fd" else f"{kind} frame"
            raise FrameError(what, arbitration_id=msg.arbitration_id, dlc=msg.dlc, device=self.name)
        try:
            status = decode_frame(
                msg.arbitration_id, bytes(msg.data), is_extended_id=msg.is_extended_id, db=self._db
            )
        except FrameError:
            self._account_rejected(msg)
            raise
        lost = self._check_counter(msg, status.counter)
        quality = Quality.OK
        if status.status is SensorStatus.WARNING:
            self.metrics.count("warnings")
        elif status.status is SensorStatus.FAULT:
            self.metrics.count("faults")
            quality = Quality.FAULT
        return CanReading(
            t=self._now(),
            speed_rpm=status.speed_rpm,
            torque_nm=status.torque_nm,
            status=status.status,
            counter=status.counter,
            quality=quality,
            frames_lost=lost,
        )

    def _account_rejected(self, msg: can.Message) -> None:
        """A classic ``SpindleStatus`` frame was rejected: it still took a counter value (not lost)."""
        if msg.arbitration_id != SPINDLE_STATUS_ID or msg.is_extended_id:
            return
        counter = frame_counter(msg.data, db=self._db)
        if counter is None:
            self._unread += 1
        else:
            self._check_counter(msg, counter)

    def _check_counter(self, msg: can.Message, counter: int) -> int:
        previous, self._last_counter = self._last_counter, counter
        unread, self._unread = self._unread, 0
        if previous is None:
            return 0
        gap = counter_gap(previous, counter)
        repeat = counter == previous and unread == 0
        gap = 0 if repeat else max(0, gap - unread)  # rejected frames in between were received
        if gap == 0 and not repeat:
            return 0
        self.metrics.count("counter_repeats" if repeat else "counter_gaps")
        self.metrics.count("frames_lost", gap)
        expected = (previous + 1) % 16
        self.note_error(
            CounterGapError(
                arbitration_id=msg.arbitration_id,
                dlc=msg.dlc,
                expected=expected,
                got=counter,
                device=self.name,
            )
        )
        return gap

    # ---------------------------------------------------------------------------------------- state
    def condition(self) -> str:
        """Why the sensor is not fully healthy right now although frames arrive ("" when it is): the
        latest frame's status byte says warning or fault. Stale data is not a condition (see ``is_stale``)."""
        if self._latest is None or self.is_stale() or self._latest.status is SensorStatus.OK:
            return ""
        r = self._latest
        return (
            f"{self.name}: sensor reports {r.status.name.lower()} (status byte {int(r.status)}) "
            f"at {r.t.isoformat()}"
        )

    def current(self) -> CanReading:
        """The latest reading, with quality ``STALE`` if nothing arrived for ``stale_after_s``.

        Raises ``NoDataError`` before the first frame."""
        latest = self.latest()
        return replace(latest, quality=Quality.STALE) if self.is_stale() else latest
