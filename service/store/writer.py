"""Buffered, retrying database writer: the service never waits for (or crashes on) the database.

``DbWriter.submit(record)`` appends to an in-memory FIFO and returns at once. A worker thread writes the
FIFO in order, in batches (one session and transaction per batch). While the database is unavailable the
records stay buffered (at most ``buffer_max``; beyond that new records are dropped and counted) and the
worker retries with exponential backoff (``retry_initial_s`` doubling up to ``retry_max_s``), probing even
when idle so that ``status().connected`` tells the truth for health checks. A record the database refuses
for good (duplicate id, missing condition) is isolated, counted in ``rejected`` and skipped, so one bad
record never blocks the rest. Outages are themselves recorded as ``DeviceEventData(device="db")`` rows,
written once the database is back.

With a ``watchdog`` (``service.store.watchdog.StatementWatchdog``) every write and probe is guarded: one that
waits longer than the watchdog's ``abort_after_s`` (a hung database) is aborted and handled like an outage;
``status().busy_s`` says how long this writer's current one has been waiting (health: ``degraded`` after a
few seconds). Both are this writer's own: the writers of one engine (a host's spindles) share its watchdog,
but one spindle's stuck write neither shows in another's status nor aborts another's write in flight
(issue 41.2). With ``heartbeat_s`` an idle, connected writer probes every ``heartbeat_s`` (``SELECT 1``), so a
database that hangs while nothing is written is noticed too, and ``last_ok_at`` stays fresh. The writers of
one engine (an instance hosting several spindles) share a ``Heartbeat``: one probe answers all of them, and a
success of any of them (a write or a probe) within ``heartbeat_s`` stands for a probe of the others.

With ``downsample=True`` (the service's writer) every sample submitted also feeds a 1-minute mean
(``service.store.downsample``), submitted when the minute is over (and at ``close()``): what retention keeps
after the raw samples are dropped. The counters count the submitted records, not these.

``flush(timeout_s)`` waits until everything submitted so far is written; ``close(timeout_s)`` flushes, stops
the thread and counts what could not be written as ``lost_on_close``.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from types import TracebackType

from sqlalchemy import text
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.records import RECORD_TYPES, DeviceEventData, Record, SampleData, SampleMinuteData
from service.logctx import in_current_context
from service.store.downsample import MinuteMeans
from service.store.errors import DatabaseUnavailableError
from service.store.repository import session_scope, write_records
from service.store.watchdog import StatementWatchdog

log = logging.getLogger(__name__)


def utc_now() -> datetime:
    return datetime.now(UTC)


@dataclass(frozen=True, kw_only=True)
class WriterStatus:
    connected: bool  # the last write or probe succeeded
    pending: int  # records buffered, not yet written
    written: int
    dropped: int  # refused by submit() because the buffer was full (or the writer closed)
    rejected: int  # refused by the database for good (see last_error)
    errors: int  # failed write/probe attempts
    lost_on_close: int  # still buffered when close() gave up
    last_error: str | None
    last_error_at: datetime | None  # UTC
    last_ok_at: datetime | None  # UTC of the last successful write or probe
    busy_s: float | None = None  # wall seconds the current write/probe has been waiting (None: idle)
    stall_s: float = 3.0  # busy_s above this: the database is hung (health: degraded)


class Heartbeat:
    """The idle probe of one engine, shared by its writers (``service.host.persistence.SharedDatabase``).

    A connected writer whose heartbeat is due calls ``beat(probe, max_age_s)``: the newest success of any
    writer of the engine younger than ``max_age_s`` is its answer; else the first caller runs ``probe()``
    (``SELECT 1``) while the others that ask meanwhile wait for it and share its result, a success or its
    ``DatabaseUnavailableError``. Every success of a writer is told to ``ok()``. Times are the writers'
    monotonic seconds (they share one clock) and their clock's UTC time. Thread-safe.
    """

    def __init__(self, *, monotonic: Callable[[], float] = time.monotonic) -> None:
        self._monotonic = monotonic
        self._probing = threading.Lock()  # held while one writer probes: the others wait for its answer
        self._lock = threading.Lock()
        self._ok: tuple[float, datetime] | None = None  # the newest success: (monotonic s, UTC)
        self._failed: tuple[float, DatabaseUnavailableError] | None = None  # the newest failed probe
        self.probes = 0

    def ok(self, mono: float, at: datetime) -> None:
        """A writer of the engine succeeded (a write or a probe) at ``mono`` (``at`` on its clock)."""
        with self._lock:
            if self._ok is None or mono >= self._ok[0]:
                self._ok = (mono, at)

    def beat(self, probe: Callable[[], tuple[float, datetime]], max_age_s: float) -> tuple[float, datetime]:
        """The engine's success to count as this writer's heartbeat (see the class docstring)."""
        asked = self._monotonic()
        with self._probing:
            with self._lock:
                ok, failed = self._ok, self._failed
            if failed is not None and failed[0] >= asked and (ok is None or failed[0] > ok[0]):
                raise failed[1]  # probed for us while we waited, and failed
            if ok is not None and (ok[0] >= asked or self._monotonic() - ok[0] < max_age_s):
                return ok
            self.probes += 1
            try:
                done = probe()
            except DatabaseUnavailableError as err:
                with self._lock:
                    self._failed = (self._monotonic(), err)
                raise
            self.ok(*done)
            return done


class DbWriter:
    """See the module docstring. Thread-safe; use as a context manager or call ``start()``/``close()``."""

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        *,
        batch_size: int = 500,
        buffer_max: int = 100_000,
        retry_initial_s: float = 0.5,
        retry_max_s: float = 30.0,
        clock: Callable[[], datetime] = utc_now,
        watchdog: StatementWatchdog | None = None,
        heartbeat_s: float | None = None,
        heartbeat: Heartbeat | None = None,  # shared by the writers of one engine (None: probes alone)
        stall_s: float = 3.0,
        monotonic: Callable[[], float] = time.monotonic,
        name: str = "chtc-db-writer",
        downsample: bool = False,
        on_write: Callable[[float], None] | None = None,
    ) -> None:
        if batch_size < 1 or buffer_max < 1 or not 0 < retry_initial_s <= retry_max_s:
            raise ValueError("need batch_size >= 1, buffer_max >= 1, 0 < retry_initial_s <= retry_max_s")
        self._factory = session_factory
        self._batch_size = batch_size
        self._buffer_max = buffer_max
        self._retry = (retry_initial_s, retry_max_s)
        self._clock = clock
        self._watchdog = watchdog
        self._heartbeat_s = heartbeat_s
        self._heartbeat = heartbeat
        self._stall_s = stall_s
        self._monotonic = monotonic
        self._last_ok_mono = -float("inf")
        self._busy_since: float | None = None  # monotonic start of this writer's current write/probe
        self._queue: deque[Record] = deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=in_current_context(self._run), name=name, daemon=True)
        self._closed = False
        self._connected = False
        self._outage_reported = False
        self._counts = {"written": 0, "dropped": 0, "rejected": 0, "errors": 0, "lost_on_close": 0}
        self._last_error: tuple[str, datetime] | None = None
        self._last_ok_at: datetime | None = None
        # 1-minute means of the samples submitted, written beside them (kept after the raw ones are dropped)
        self._minutes = MinuteMeans() if downsample else None
        # told the wall seconds of every batch written (commit included): /metrics chtc_db_write_seconds
        self._on_write = on_write

    # --- caller side ------------------------------------------------------------------------------
    def start(self) -> DbWriter:
        self._thread.start()
        return self

    def submit(self, record: Record) -> bool:
        """Buffer one record; False if it was dropped (buffer full or writer closed). Never blocks on I/O."""
        if not isinstance(record, RECORD_TYPES):
            raise TypeError(f"not a database record: {type(record).__name__}")
        with self._cond:
            if self._closed or len(self._queue) >= self._buffer_max:
                self._counts["dropped"] += 1
                return False
            self._queue.append(record)
            if self._minutes is not None and isinstance(record, SampleData):
                done = self._minutes.add(record)
                if done is not None:
                    self._queue.append(done)
            self._cond.notify_all()
            return True

    def submit_many(self, records: Iterable[Record]) -> int:
        """Buffer records in order; returns how many were accepted."""
        return sum(self.submit(r) for r in records)

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every record submitted so far is written (or rejected); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue, timeout=timeout_s)

    def close(self, timeout_s: float = 10.0) -> WriterStatus:
        """Flush (up to ``timeout_s``), stop the worker and return the final status."""
        with self._cond:
            self._closed = True
            last = self._minutes.flush() if self._minutes is not None else None
            if last is not None:
                self._queue.append(last)
        if self._thread.is_alive():
            self.flush(timeout_s)
            self._stop.set()
            with self._cond:
                self._cond.notify_all()
            self._thread.join(timeout=max(timeout_s, 1.0))
        with self._cond:
            if self._queue:
                self._counts["lost_on_close"] += len(self._queue)
                log.error("database writer closed with %d records not written", len(self._queue))
                self._queue.clear()
                self._cond.notify_all()
        return self.status()

    def status(self) -> WriterStatus:
        with self._cond:
            err = self._last_error
            return WriterStatus(
                connected=self._connected,
                pending=len(self._queue),
                last_error=err[0] if err else None,
                last_error_at=err[1] if err else None,
                last_ok_at=self._last_ok_at,
                busy_s=self._busy_s(),
                stall_s=self._stall_s,
                **self._counts,
            )

    def __enter__(self) -> DbWriter:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # --- worker side ------------------------------------------------------------------------------
    def _run(self) -> None:
        failures = 0
        while not self._stop.is_set():
            batch = self._next_batch()
            try:
                if batch:
                    self._write(batch)
                elif not self._connected:
                    self._probe()
                elif self._heartbeat_due():
                    self._beat()
                else:
                    continue
                failures = 0
            except DatabaseUnavailableError as err:
                self._on_unavailable(err)
                delay = min(self._retry[1], self._retry[0] * 2.0 ** min(failures, 30))
                failures += 1
                self._stop.wait(delay)
            except Exception as err:  # never let the thread die: count, log, back off
                log.exception("database writer: unexpected error")
                self._note_error(f"unexpected: {err!r}")
                self._stop.wait(self._retry[0])

    def _heartbeat_due(self) -> bool:
        hb = self._heartbeat_s
        return hb is not None and self._monotonic() - self._last_ok_mono >= hb

    def _next_batch(self) -> list[Record]:
        with self._cond:
            if not self._queue and self._connected:
                wait = 1.0 if self._heartbeat_s is None else min(1.0, self._heartbeat_s)
                self._cond.wait_for(lambda: self._queue or self._stop.is_set(), timeout=wait)
            return list(itertools.islice(self._queue, self._batch_size))

    def _busy_s(self) -> float | None:
        """Wall seconds this writer's current write/probe has been waiting (None: idle, or no watchdog)."""
        since = self._busy_since
        return None if since is None or self._watchdog is None else self._monotonic() - since

    @contextlib.contextmanager
    def _busy(self) -> Iterator[None]:
        """This writer waits on the database (its own write or probe, or the engine's shared heartbeat)."""
        outer = self._busy_since is not None
        if not outer:
            self._busy_since = self._monotonic()
        try:
            yield
        finally:
            if not outer:
                self._busy_since = None

    @contextlib.contextmanager
    def _guard(self, what: str) -> Iterator[None]:
        with self._busy(), contextlib.nullcontext() if self._watchdog is None else self._watchdog.guard(what):
            yield

    def _write(self, batch: Sequence[Record]) -> None:
        started = time.perf_counter()
        try:
            what = f"write {len(batch)} records"
            with self._guard(what), session_scope(self._factory, what) as session:
                write_records(session, batch)
        except DatabaseUnavailableError:
            raise
        except Exception:  # refused for good (or a bug): find the culprits one by one
            self._isolate(batch)
            return
        if self._on_write is not None:
            self._on_write(time.perf_counter() - started)
        self._done(len(batch), "written", derived=_derived(batch))

    def _isolate(self, batch: Sequence[Record]) -> None:
        """Write one by one to find the records the database refuses; skip those, keep order for the rest."""
        for record in batch:
            try:
                what = f"write {type(record).__name__}"
                with self._guard(what), session_scope(self._factory, what) as session:
                    write_records(session, [record])
            except DatabaseUnavailableError:
                raise
            except Exception as err:
                log.warning("database writer: record rejected: %s", err)
                self._note_error(str(err))
                self._done(1, "rejected", derived=_derived([record]))
            else:
                self._done(1, "written", derived=_derived([record]))

    def _probe(self) -> None:
        self._select_one()
        self._mark_ok()

    def _select_one(self) -> tuple[float, datetime]:
        """``SELECT 1``; when it answered (monotonic s, clock)."""
        with self._guard("probe"), session_scope(self._factory, "probe") as session:
            session.execute(text("SELECT 1"))
        return self._monotonic(), self._clock()

    def _beat(self) -> None:
        """The idle heartbeat: a probe of its own, or the engine's shared one (``Heartbeat``)."""
        if self._heartbeat is None:
            self._probe()
            return
        assert self._heartbeat_s is not None
        with self._busy():
            mono, at = self._heartbeat.beat(self._select_one, self._heartbeat_s)
        with self._cond:
            if mono > self._last_ok_mono:
                self._last_ok_mono, self._last_ok_at = mono, at

    def _done(self, n: int, counter: str, *, derived: int = 0) -> None:
        """``n`` records off the queue; the counters count what was submitted (not the minute means)."""
        with self._cond:
            for _ in range(min(n, len(self._queue))):  # close() may have given up on these already
                self._queue.popleft()
            self._counts[counter] += n - derived
            self._cond.notify_all()
        self._mark_ok()

    def _mark_ok(self) -> None:
        at, mono = self._clock(), self._monotonic()
        with self._cond:
            was = self._connected
            self._connected = True
            self._last_ok_at = at
            self._last_ok_mono = mono
            reported, self._outage_reported = self._outage_reported, False
        if self._heartbeat is not None:
            self._heartbeat.ok(mono, at)
        if not was:
            log.info("database writer: connected")
        if reported:
            self.submit(
                DeviceEventData(t=self._clock(), device="db", kind="available", detail="writes resumed")
            )

    def _on_unavailable(self, err: DatabaseUnavailableError) -> None:
        with self._cond:
            self._connected = False
            reported, self._outage_reported = self._outage_reported, True
        self._note_error(str(err))
        if not reported:
            log.warning("database writer: database unavailable, buffering: %s", err)
            self.submit(
                DeviceEventData(t=self._clock(), device="db", kind="unavailable", detail=str(err)[:500])
            )

    def _note_error(self, message: str) -> None:
        with self._cond:
            self._counts["errors"] += 1
            self._last_error = (message, self._clock())


def _derived(batch: Sequence[Record]) -> int:
    """Records the writer made itself (minute means), not counted as submitted ones."""
    return sum(isinstance(r, SampleMinuteData) for r in batch)
