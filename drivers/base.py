"""One small base class for every acquisition source (modelled on python-can's ``BusABC``).

A ``Source`` owns the shared behaviour once: the timeout around every device call, connecting lazily,
bounded exponential reconnect backoff with jitter, staleness, error bookkeeping and metrics. A driver
implements three hooks:

- ``_connect()``: open the link (raise ``DeviceUnavailableError`` on failure);
- ``_read_internal()``: one reading (raise ``DeviceError`` subclasses; bare ``TimeoutError`` is translated);
- ``_disconnect()``: drop the link (must not raise).

``read()`` never sleeps for backoff: while a reconnect is not yet due it raises ``DeviceUnavailableError``
saying when the next attempt is, so a poll loop keeps its rhythm and the caller always gets an answer.
``run()`` is that poll loop. After an outage the next attempt is at most ``Backoff.max_s`` (default 2 s) away.

Failed reads are logged by ``ErrorLog`` (logger ``drivers``): one line per distinct error (class and message
with numbers ignored), no traceback; repeats of it within ``log_every_s`` (default 60 s) are counted and
reported on its next line.

Clocks are injected: ``clock`` is monotonic seconds (timeouts, backoff, staleness), ``now`` is the UTC
wall clock used for timestamps; ``rng`` draws the jitter; ``sleep`` is what ``run()`` waits with.
"""

from __future__ import annotations

import asyncio
import logging
import random
import re
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from types import TracebackType
from typing import Generic, Self, TypeVar

import numpy as np
import numpy.typing as npt

from drivers.errors import DeviceError, DeviceTimeoutError, DeviceUnavailableError, DriverError, NoDataError

T = TypeVar("T")
R = TypeVar("R")
Clock = Callable[[], float]
WallClock = Callable[[], datetime]
Sleep = Callable[[float], Awaitable[None]]


def utc_now() -> datetime:
    """Current time as an aware UTC ``datetime``."""
    return datetime.now(UTC)


_NUMBER = re.compile(r"\d+(\.\d+)?")


class ErrorLog:
    """Logs device errors one line each, rate-limited per distinct error.

    Two errors are the same when their class and their message with every number replaced agree (so a
    transaction id or a byte count that changes from poll to poll does not make a new error). The first
    occurrence is logged at once; later ones only when ``every_s`` seconds have passed since that error's
    last line, with the number of repeats in between. ``clock`` is monotonic seconds.
    """

    def __init__(
        self, logger: logging.Logger, *, every_s: float = 60.0, clock: Clock = time.monotonic
    ) -> None:
        self.logger, self.every_s, self._clock = logger, every_s, clock
        self._seen: dict[tuple[str, str], tuple[float, int]] = {}  # key -> (last logged at, repeats since)

    def error(self, err: BaseException) -> bool:
        """Count ``err``; log it if it is new or due. Returns whether a line was written."""
        key = (type(err).__name__, _NUMBER.sub("#", str(err)))
        now = self._clock()
        last = self._seen.get(key)
        if last is not None and now - last[0] < self.every_s:
            self._seen[key] = (last[0], last[1] + 1)
            return False
        repeats = f" (repeated {last[1]} times in {now - last[0]:.0f} s)" if last and last[1] else ""
        self.logger.warning("%s: %s%s", type(err).__name__, err, repeats)
        self._seen[key] = (now, 0)
        return True


@dataclass(frozen=True)
class Backoff:
    """Reconnect delays: ``initial_s · factor^(attempt-1)``, capped at ``max_s`` (s), minus up to ``jitter``
    (a fraction) drawn at random so that many clients do not reconnect in lockstep.

    Never exceeds ``max_s``."""

    initial_s: float = 0.1
    factor: float = 2.0
    max_s: float = 2.0
    jitter: float = 0.25

    def delay_s(self, attempt: int, rng: random.Random) -> float:
        """Delay before reconnect attempt number ``attempt`` (1 = first retry), in seconds."""
        base = min(self.max_s, self.initial_s * self.factor ** max(attempt - 1, 0))
        return base * (1.0 - self.jitter * rng.random())


@dataclass
class SourceMetrics:
    """Counters of one source; ``snapshot()`` gives a plain dict for metrics export and health pages.

    ``errors`` counts failed reads by error class name; ``events`` counts driver-specific happenings
    (``frames``, ``counter_gaps``, ``frames_lost``, ``unknown_ids``, ``restarts``, ``stale`` …).
    """

    polls: int = 0
    reads_ok: int = 0
    connects: int = 0
    reconnects: int = 0
    connect_failures: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    events: dict[str, int] = field(default_factory=dict)
    last_error: str = ""
    last_error_t: datetime | None = None
    last_ok_t: datetime | None = None

    def count_error(self, err: BaseException, t: datetime) -> None:
        """Count ``err`` by its class name and remember it as the last error."""
        key = type(err).__name__
        self.errors[key] = self.errors.get(key, 0) + 1
        self.last_error, self.last_error_t = str(err), t

    def count(self, event: str, n: int = 1) -> None:
        """Add ``n`` to the named event counter."""
        self.events[event] = self.events.get(event, 0) + n

    def snapshot(self) -> dict[str, object]:
        """A copy safe to hand to another thread (timestamps as ISO-8601 UTC strings)."""
        return {
            "polls": self.polls,
            "reads_ok": self.reads_ok,
            "connects": self.connects,
            "reconnects": self.reconnects,
            "connect_failures": self.connect_failures,
            "errors": dict(self.errors),
            "events": dict(self.events),
            "last_error": self.last_error,
            "last_error_t": self.last_error_t.isoformat() if self.last_error_t else None,
            "last_ok_t": self.last_ok_t.isoformat() if self.last_ok_t else None,
        }


class Source(Generic[T]):
    """Base of the acquisition drivers: ``read()``, ``close()``, ``async with``, ``run()``.

    ``timeout_s`` bounds every ``_connect``/``_read_internal`` call; ``stale_after_s`` is how long after the
    last good reading the source counts as stale (``is_stale()``). A source belongs to one event loop and
    one reading task (``run()`` or a caller of ``read()``); ``latest()``, ``is_stale()`` and
    ``metrics.snapshot()`` may be called from anywhere.
    """

    read_what = "read"  # named in timeout messages: "no answer to <read_what> within 1 s"

    def __init__(
        self,
        *,
        name: str,
        timeout_s: float = 1.0,
        stale_after_s: float = 5.0,
        backoff: Backoff | None = None,
        clock: Clock = time.monotonic,
        now: WallClock = utc_now,
        rng: random.Random | None = None,
        sleep: Sleep = asyncio.sleep,
        log_every_s: float = 60.0,
    ) -> None:
        if timeout_s <= 0 or stale_after_s <= 0:
            raise ValueError(f"{name}: timeout_s and stale_after_s must be > 0")
        self.name = name
        self.timeout_s = timeout_s
        self.stale_after_s = stale_after_s
        self.backoff = backoff or Backoff()
        self.metrics = SourceMetrics()
        self._clock, self._now, self._sleep = clock, now, sleep
        self._rng = rng or random.Random()
        self.error_log = ErrorLog(logging.getLogger("drivers"), every_s=log_every_s, clock=clock)
        self._connected = False
        self._ever_connected = False
        self._closed = False
        self._failures = 0  # consecutive failed attempts, drives the backoff
        self._next_attempt_at = float("-inf")
        self._latest: T | None = None
        self._latest_at = float("-inf")
        # called with the duration (s, on ``clock``) of every successful read (e.g. a poll-latency histogram)
        self.on_read_s: Callable[[float], None] | None = None

    # --------------------------------------------------------------------------------------------- hooks
    async def _connect(self) -> None:
        """Open the link to the device. Override."""

    async def _read_internal(self) -> T:
        """Produce one reading. Override."""
        raise NotImplementedError

    async def _disconnect(self) -> None:
        """Drop the link. Override; must not raise."""

    def _read_timeout_s(self) -> float:
        """Budget for one ``_read_internal`` call in s (``timeout_s``; override for multi-request reads)."""
        return self.timeout_s

    def _read_ready(self) -> bool:
        """True when ``_read_internal`` will return without waiting (data already buffered): the read then
        skips the timeout machinery. Override in push-style drivers."""
        return False

    def _needs_reconnect(self, err: DeviceError) -> bool:
        """Whether ``err`` means the link must be re-established (timeouts and lost connections do)."""
        return isinstance(err, DeviceTimeoutError | DeviceUnavailableError)

    # ------------------------------------------------------------------------------------------ public API
    @property
    def connected(self) -> bool:
        """True while the link is believed up."""
        return self._connected

    @property
    def closed(self) -> bool:
        """True after ``close()``."""
        return self._closed

    def retry_in_s(self) -> float:
        """Seconds until the next reconnect attempt is due (0 when connected or due now)."""
        return 0.0 if self._connected else max(0.0, self._next_attempt_at - self._clock())

    async def connect(self) -> None:
        """Open the link now instead of on the first ``read()``; failures count towards the backoff."""
        if self._closed:
            raise DeviceUnavailableError("source is closed", device=self.name)
        try:
            await self._ensure_connected()
        except DeviceError as err:
            await self._on_failure(err)
            raise

    async def read(self) -> T:
        """One reading from the device. Connects (or reconnects, once backoff allows) first.

        Raises ``DeviceUnavailableError`` (link down, or reconnect not yet due), ``DeviceTimeoutError``,
        ``ProtocolError`` subclasses; each is counted in ``metrics`` before it propagates.
        """
        if self._closed:
            raise DeviceUnavailableError("source is closed", device=self.name)
        self.metrics.polls += 1
        wait = self.retry_in_s()
        if wait > 0:
            self.metrics.count("polls_while_down")
            raise DeviceUnavailableError(
                f"link down, reconnect attempt {self._failures + 1} in {wait:.2f} s "
                f"(last error: {self.metrics.last_error or 'none'})",
                device=self.name,
            )
        try:
            await self._ensure_connected()
            started = self._clock()
            if self._connected and self._read_ready():
                reading = await self._read_internal()
            else:
                reading = await self._with_timeout(
                    self._read_internal(), self.read_what, self._read_timeout_s()
                )
        except DeviceError as err:
            await self._on_failure(err)
            raise
        self._failures = 0
        self._latest, self._latest_at = reading, self._clock()
        if self.on_read_s is not None:
            self.on_read_s(self._latest_at - started)
        self.metrics.reads_ok += 1
        self.metrics.last_ok_t = self._now()
        return reading

    def latest(self) -> T:
        """The last good reading; raises ``NoDataError`` before the first one."""
        if self._latest is None:
            raise NoDataError(f"{self.name}: no reading yet")
        return self._latest

    def latest_age_s(self) -> float:
        """Seconds since the last good reading (``inf`` before the first)."""
        return self._clock() - self._latest_at

    def is_stale(self) -> bool:
        """True when the last good reading is older than ``stale_after_s`` (or there is none)."""
        return self.latest_age_s() > self.stale_after_s

    def condition(self) -> str:
        """A reason the device is degraded now although reads succeed ("" when none). Override."""
        return ""

    def note_error(self, err: DriverError) -> None:
        """Count an error that did not abort the read (e.g. a counter gap) and remember it."""
        self.metrics.count_error(err, self._now())

    async def close(self) -> None:
        """Disconnect and refuse further reads. Idempotent."""
        if not self._closed:
            self._closed = True
            await self._drop_link()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def run(
        self,
        *,
        interval_s: float,
        on_reading: Callable[[T], None] | None = None,
        on_error: Callable[[DeviceError], None] | None = None,
    ) -> None:
        """Read every ``interval_s`` seconds until closed or cancelled. Errors are counted (and passed to
        ``on_error``), never raised; while the link is down the loop waits for the next reconnect attempt,
        so reconnecting after an outage takes at most ``max(interval_s, backoff.max_s)``.

        A cancellation swallowed during ``read()`` (seen on shutdown in the end-to-end test: the DAQ loop
        went on after ``cancel()``; a client library or a timeout racing the cancel can consume it) is
        re-raised here, so cancelling the loop always ends it."""
        task = asyncio.current_task()
        while not self._closed:
            started = self._clock()
            try:
                reading = await self.read()
            except DeviceError as err:
                if on_error is not None:
                    on_error(err)
            else:
                if on_reading is not None:
                    on_reading(reading)
            wait = max(0.0, interval_s - (self._clock() - started))
            if not self._connected:
                wait = max(wait, self.retry_in_s()) if interval_s > 0 else self.retry_in_s()
            if task is not None and task.cancelling():
                raise asyncio.CancelledError
            await self._sleep(wait)

    # ------------------------------------------------------------------------------------------- internals
    async def _with_timeout(self, aw: Awaitable[R], what: str, timeout_s: float) -> R:
        # asyncio.timeout, not wait_for: on Python 3.11 wait_for can swallow a cancellation (gh-86296).
        try:
            async with asyncio.timeout(timeout_s):
                return await aw
        except DeviceError:
            raise
        except TimeoutError as err:
            raise DeviceTimeoutError(f"no answer to {what} within {timeout_s:g} s", device=self.name) from err

    async def _ensure_connected(self) -> None:
        if self._connected:
            return
        try:
            await self._with_timeout(self._connect(), "connect", self.timeout_s)
        except DeviceError:
            self.metrics.connect_failures += 1
            await self._disconnect()
            raise
        self._connected = True
        self.metrics.connects += 1
        if self._ever_connected:
            self.metrics.reconnects += 1
        self._ever_connected = True

    async def _on_failure(self, err: DeviceError) -> None:
        self.metrics.count_error(err, self._now())
        self.error_log.error(err)
        if self._needs_reconnect(err) or not self._connected:
            self._failures += 1
            self._next_attempt_at = self._clock() + self.backoff.delay_s(self._failures, self._rng)
            await self._drop_link()

    async def _drop_link(self) -> None:
        self._connected = False
        await self._disconnect()


class StuckDetector:
    """Per-channel "value has not changed" bookkeeping.

    ``update(values)`` is called once per *new device sample* (not per poll: a DAQ polled faster than it
    samples repeats values legitimately). A channel is stuck once its value stayed within ``tolerance`` of
    the value where the run started for ``samples`` consecutive samples. NaN never counts as a repeat.
    """

    def __init__(self, n_channels: int, *, samples: int, tolerance: float = 0.0) -> None:
        if samples < 2:
            raise ValueError(f"stuck samples must be >= 2, got {samples}")
        self.samples, self.tolerance = samples, tolerance
        self._ref = np.full(n_channels, np.nan)
        self._run = np.zeros(n_channels, dtype=np.int64)

    def update(self, values: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """Feed one sample (n,); returns the stuck mask (n,)."""
        same = np.abs(values - self._ref) <= self.tolerance  # False where either is NaN
        self._run = np.where(same, self._run + 1, 1)
        self._ref = np.where(same, self._ref, values)
        return self.stuck()

    def stuck(self) -> npt.NDArray[np.bool_]:
        """Current stuck mask (n,) without feeding a sample."""
        return self._run >= self.samples

    def reset(self) -> None:
        """Forget history (after a device restart)."""
        self._ref[:] = np.nan
        self._run[:] = 0
