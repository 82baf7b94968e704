"""Database at the edge of the service: migrate, restore the state of the last run, buffered writes.

``open_persistence(settings.database, migrate=...)`` builds the engine and the session factory, optionally
migrates, reads back what the service needs to resume (``Restored``: the last successful identification,
the newest result per condition for warm starts, recent conditions, the offset baseline, the compensation
zero, the next free ids) and starts the
buffered writer (``service.store.writer.DbWriter``).

The database being down never stops the service:

- at start-up: the service starts without restored state and says so once (a logged warning); ids continue
  from a time-based base (``int(epoch s) * 1000``) so they cannot collide with rows of earlier runs, unless
  the database answers before the first id is issued: then they continue from the stored ones
  (``Persistence.on_open``, ``service.core.idcounter``); records are held in a ``GateSink`` until the
  schema is known to be in place (migrated / checked), retried in the background;
- later: the writer buffers and retries (E's ``DbWriter``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping
from contextlib import nullcontext
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Any, TypeVar

from service.contracts.calibration import Calibration
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import ProbeMeasurement
from service.contracts.records import Record
from service.contracts.reference import CompensationReference
from service.contracts.snapshots import ConditionState, IdentificationRecord
from service.core.config import Restored
from service.core.jobbook import MAP_METHOD
from service.identify.detector import OperatingPoint
from service.identify.scheduler import PastResult
from service.serve.histogram import Histogram
from service.serve.views import condition_from_row, row_to_record
from service.store.errors import SchemaError

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine
    from sqlalchemy.orm import Session, sessionmaker

    from service.contracts.calibration import Calibration
    from service.contracts.checkpoint import LiveCheckpoint
    from service.contracts.mechanics import MechanicsCalibration
    from service.contracts.probe import ProbeMeasurement
    from service.contracts.reference import CompensationReference
    from service.identify.speedmap import SpeedMap
    from service.settings import DatabaseSettings, SpindleSettings
    from service.store.reads import DbReads
    from service.store.retention import RetentionReport
    from service.store.watchdog import StatementWatchdog
    from service.store.writer import DbWriter, Heartbeat, WriterStatus

__all__ = ["GateSink", "Persistence", "SharedDatabase", "open_persistence", "restore"]

log = logging.getLogger(__name__)
T = TypeVar("T")
# chtc_db_write_seconds: fine around the 50 ms a fleet's writes must stay under (issue 29)
DB_WRITE_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


def restore(
    session_factory: sessionmaker[Session],
    *,
    limit: int = 100,
    on_problem: Callable[[str], None] | None = None,
) -> Restored:
    """The state of the previous run from the database (raises ``service.store.errors.DatabaseError``).

    A stored offset baseline that cannot be used is reported to ``on_problem`` (and logged) and left in the
    table; the service then starts without a baseline and everything else is restored.
    """
    from service.store.repository import (
        last_served_identification,
        last_speed_map_state,
        latest_per_condition,
        list_conditions,
        max_ids,
        session_scope,
    )

    with session_scope(session_factory, "restore state") as session:
        cond_max, ident_max = max_ids(session)
        last_row = last_served_identification(session)
        last = row_to_record(last_row) if last_row is not None else None
        # the newest map fit (combined mode: the last served one may be a per-condition identification)
        map_row = last_row
        if last_row is not None and last_row.method != MAP_METHOD:
            map_row = last_served_identification(session, method=MAP_METHOD)
        map_last = last if map_row is last_row else row_to_record(map_row) if map_row is not None else None
        latest = latest_per_condition(session, limit=limit)
        history = tuple(
            PastResult(
                condition_id=int(r.condition_id),
                point=OperatingPoint(
                    speed_rpm=r.condition.speed_rpm,
                    torque_nm=r.condition.torque_nm,
                    ambient_c=r.condition.ambient_c,
                ),
                h=h,
            )
            for r in reversed(latest)  # oldest first: the scheduler prefers the newest on ties
            if (h := _complete(r.h)) is not None
        )
        rows = list_conditions(session, limit=50).items
        conditions = tuple(condition_from_row(c, state=ConditionState.STABLE) for c in rows)
        calibration = _restore_calibration(session, on_problem)
        reference = _restore_reference(session, on_problem)
        mechanics = _restore_mechanics(session, on_problem)
        probes = _restore_probes(session, on_problem)
        live = _restore_live(session, on_problem)
        state = last_speed_map_state(session)
        map_state = None if state is None else (int(state.identification_id), state.state)
    return Restored(
        live=live,
        reference=reference,
        mechanics=mechanics,
        probes=probes,
        speed_map=_restore_map(map_last, map_state, on_problem),
        map_last=map_last,
        calibration=calibration,
        last=last,
        history=history,
        conditions=conditions,
        next_condition_id=cond_max + 1,
        next_identification_id=ident_max + 1,
    )


def _restore_map(
    last: IdentificationRecord | None,
    state: tuple[int, Any] | None,
    on_problem: Callable[[str], None] | None,
) -> SpeedMap | None:
    """The speed map of the last served map fit, as restored: stale until re-fitted (None: no map fit).
    Its whole state (with the covariance) is the spindle's ``speed_map_state`` row when that row is this
    fit's; rows stored before revision 0007 carry it in their diagnostics."""
    from service.identify.speedmap import SpeedMap, SpeedMapError

    if last is None or not isinstance(last.data.diagnostics, Mapping):
        return None
    stored = last.data.diagnostics.get("speed_map")
    if stored is None:
        return None
    if state is not None and state[0] == last.id:
        stored = state[1]
    try:
        return SpeedMap.from_json(stored, identification_id=last.id, restored=True)
    except SpeedMapError as err:
        text = f"stored speed map of identification {last.id} not restored ({err}); starting cold"
        log.warning("%s", text)
        if on_problem is not None:
            on_problem(text)
        return None


def _restore_or_report(
    read: Callable[[Session], T | None],
    session: Session,
    what: str,
    then: str,
    on_problem: Callable[[str], None] | None,
) -> T | None:
    """``read(session)``; a stored row it refuses (``RecordRejectedError``, naming the row) is logged and told
    to ``on_problem`` as "stored {what} not restored (...); {then}", and None is restored in its place."""
    from service.store.errors import RecordRejectedError

    try:
        return read(session)
    except RecordRejectedError as err:
        text = f"stored {what} not restored ({err}); {then}"
        log.warning("%s", text)
        if on_problem is not None:
            on_problem(text)
        return None


def _restore_calibration(session: Session, on_problem: Callable[[str], None] | None) -> Calibration | None:
    from service.store.calibrations import restore_calibration

    return _restore_or_report(
        restore_calibration, session, "sensor offset baseline", "starting without a baseline", on_problem
    )


def _restore_reference(
    session: Session, on_problem: Callable[[str], None] | None
) -> CompensationReference | None:
    from service.store.references import restore_reference

    then = "/compensation is not usable until one is set"
    return _restore_or_report(restore_reference, session, "compensation zero", then, on_problem)


def _restore_mechanics(
    session: Session, on_problem: Callable[[str], None] | None
) -> MechanicsCalibration | None:
    from service.store.mechanics import restore_mechanics

    then = "the growth is served with the described mechanics, uncalibrated"
    return _restore_or_report(restore_mechanics, session, "mechanics calibration", then, on_problem)


def _restore_probes(
    session: Session, on_problem: Callable[[str], None] | None
) -> tuple[ProbeMeasurement, ...]:
    from service.store.probes import restore_probes

    then = "the mechanics are served without the probe readings"
    return _restore_or_report(restore_probes, session, "probe readings", then, on_problem) or ()


def _restore_live(session: Session, on_problem: Callable[[str], None] | None) -> LiveCheckpoint | None:
    from service.store.livestate import restore_live_state

    then = "the filter starts from its prior"
    return _restore_or_report(restore_live_state, session, "live state", then, on_problem)


def fallback_restored(now_s: float | None = None) -> Restored:
    """No database at start-up: empty state, ids from a time-based base (no collision with stored rows)."""
    base = int(now_s if now_s is not None else time.time()) * 1000
    return Restored(next_condition_id=base, next_identification_id=base)


class GateSink:
    """Holds records until ``open(writer)``, then forwards everything (in order) to the writer."""

    def __init__(self, *, max_held: int = 1_000_000) -> None:
        self.writer: DbWriter | None = None
        self.held: list[Record] = []
        self.max_held = max_held
        self.write_latency = Histogram(DB_WRITE_BUCKETS_S)  # each batch's write and commit, wall s
        self.dropped = 0
        self.last_error = "database not reachable at start-up (schema not checked yet)"

    def submit(self, record: Record) -> bool:
        if self.writer is not None:
            return bool(self.writer.submit(record))
        if len(self.held) >= self.max_held:
            self.dropped += 1
            return False
        self.held.append(record)
        return True

    def open(self, writer: DbWriter) -> None:
        held, self.held = self.held, []
        self.writer = writer
        for record in held:
            writer.submit(record)

    def status(self) -> WriterStatus:
        if self.writer is not None:
            return self.writer.status()
        from service.store.writer import WriterStatus

        return WriterStatus(
            connected=False,
            pending=len(self.held),
            written=0,
            dropped=self.dropped,
            rejected=0,
            errors=0,
            lost_on_close=0,
            last_error=self.last_error,
            last_error_at=None,
            last_ok_at=None,
        )


@dataclass(kw_only=True)
class Persistence:
    """Engine, sessions, the gated writer and what was restored."""

    url: str
    engine: Engine
    session_factory: sessionmaker[Session]
    sink: GateSink
    restored: Restored
    restored_from_db: bool
    settings: DatabaseSettings
    migrate: bool
    on_event: Callable[[str], None] = field(default=lambda _m: None)
    clock: Callable[[], datetime] | None = None  # the service's clock (None: UTC wall clock)
    # the writer's own engine and pool (a hung read never blocks a write)
    writer_engine: Engine | None = None
    writer_factory: sessionmaker[Session] | None = None
    writer_watchdog: StatementWatchdog | None = None
    reads: DbReads | None = None  # API reads, bounded and with a deadline
    read_watchdog: StatementWatchdog | None = None
    # told the database's next free (condition, identification) ids when it answers after start-up
    on_open: Callable[[int, int], None] | None = None
    spindle: SpindleSettings | None = None  # whose rows (None: the default spindle)
    owns_engines: bool = True  # False: the engines are a SharedDatabase's, closed by its owner
    heartbeat: Heartbeat | None = None  # the writer engine's idle probe (a SharedDatabase's, shared)
    retention: bool = True  # run the retention pass (it covers every spindle: one per database suffices)
    # the clock is a log's or a plant's (replay, demo): the retention pass ages rows by the newest stored
    # sample, not by the clock (a replayed log is older than raw_days by the wall clock: issue 41)
    log_time: bool = False
    _task: asyncio.Task[None] | None = None
    _retention_task: asyncio.Task[None] | None = None
    last_retention: RetentionReport | None = None

    async def ensure_open(self, *, retry_s: float = 2.0) -> None:
        """Retry migration/check until the database answers, then open the writer (background task)."""
        while self.sink.writer is None:
            try:
                await asyncio.to_thread(self._prepare_guarded)
            except Exception as err:  # database down or schema missing: keep buffering, try again
                text = _describe(err)
                if text != self.sink.last_error:  # logged once per distinct problem, not every retry
                    log.info("database not ready: %s", text)
                self.sink.last_error = text
                await asyncio.sleep(retry_s)
                continue
            if self.on_open is not None and not self.restored_from_db:
                await self._tell_ids(self.on_open)
            factory = self.writer_factory or self.session_factory
            self.sink.open(
                _start_writer(
                    factory,
                    self.settings,
                    clock=self.clock,
                    watchdog=self.writer_watchdog,
                    on_write=self.sink.write_latency.observe,
                    heartbeat=self.heartbeat,
                )
            )
            self.on_event(
                f"db: connected ({_safe_url(self.url)}), writing {len(self.sink.held)} held records"
            )

    async def _tell_ids(self, on_open: Callable[[int, int], None]) -> None:
        """The stored ids, to continue from (``service.core.idcounter``); a failed read keeps the base."""
        from service.store.repository import max_ids, session_scope

        def read() -> tuple[int, int]:
            with session_scope(self.session_factory, "read the largest ids") as session:
                return max_ids(session)

        try:
            cond_max, ident_max = await asyncio.to_thread(read)
        except Exception as err:  # the next write finds the outage; ids keep their collision-free base
            log.warning("db: could not read the stored ids (%s); ids keep their start-up base", err)
            return
        on_open(cond_max + 1, ident_max + 1)

    def _prepare_guarded(self) -> None:
        _prepare_schema(self.engine, self.migrate, self.spindle, watchdog=self.read_watchdog)

    def start_background(self) -> None:
        if self.sink.writer is None and self._task is None:
            self._task = asyncio.ensure_future(self.ensure_open())
        db = self.settings
        if self.retention and self._retention_task is None and (db.raw_days > 0 or db.minute_days > 0):
            self._retention_task = asyncio.ensure_future(self._retention_loop())

    async def _retention_loop(self) -> None:
        """``service.store.retention.retention_pass`` every ``database.retention_every_s`` (the first once
        the writer is open); a failed pass is logged and tried again at the next period."""
        while True:
            if self.sink.writer is not None:
                try:
                    self.last_retention = await asyncio.to_thread(self.retention_once)
                except Exception as err:
                    log.warning(
                        "db: retention pass failed (%s); next try in %g s",
                        err,
                        self.settings.retention_every_s,
                    )
                else:
                    self.on_event(f"db: retention pass: {_retention_text(self.last_retention)}")
                await asyncio.sleep(self.settings.retention_every_s)
            else:
                await asyncio.sleep(5.0)

    def retention_once(self) -> RetentionReport:
        from datetime import UTC
        from datetime import datetime as _dt

        from service.store.retention import retention_pass

        now = self.clock() if self.clock is not None else _dt.now(UTC)
        if self.log_time:
            from service.store.newest import newest_sample_time

            now = newest_sample_time(self.writer_engine or self.engine) or now
        db = self.settings
        return retention_pass(
            self.writer_engine or self.engine, now=now, raw_days=db.raw_days, minute_days=db.minute_days
        )

    def close(self, timeout_s: float = 10.0) -> WriterStatus | None:
        if self._retention_task is not None:
            self._retention_task.cancel()
        if self._task is not None:
            self._task.cancel()
        status = None
        if self.sink.writer is not None:
            status = self.sink.writer.close(timeout_s)
        if self.reads is not None:
            self.reads.close()
        if not self.owns_engines:
            return status
        for watchdog in (self.writer_watchdog, self.read_watchdog):
            if watchdog is not None:
                watchdog.close()
        self.engine.dispose()
        if self.writer_engine is not None:
            self.writer_engine.dispose()
        return status


def _describe(err: BaseException) -> str:
    """What the writer's status and the start-up event say: the schema problem, or the unreachable server."""
    if isinstance(err, SchemaError):
        return str(err)
    return f"database not reachable: {err}"


def _retention_text(r: RetentionReport) -> str:
    return (
        f"{len(r.partitions_dropped)} partitions dropped, {r.raw_rows_deleted} raw and "
        f"{r.minute_rows_deleted} minute rows deleted, {r.minutes_backfilled} minutes backfilled "
        f"in {r.seconds:.2f} s"
    )


def _prepare_schema(
    engine: Engine,
    migrate: bool,
    spindle: SpindleSettings | None = None,
    *,
    watchdog: StatementWatchdog | None = None,
) -> None:
    """Migrate (or check the revision), then register the spindle (every row refers to it).

    A migration runs as long as it needs (20 spindle-days: ~45 s): on PostgreSQL on an engine of its own,
    without the serving statement timeout and outside ``watchdog`` (``service.store.migrate``); the check and
    the registration are serving work, under ``watchdog``."""
    from service.store.migrate import current_revision, head_revision, upgrade

    sid = spindle.id if spindle is not None else None
    if migrate:
        upgrade(_migration_target(engine), spindle_id=sid)
    with nullcontext() if watchdog is None else watchdog.guard("check the schema"):
        if not migrate:
            _check_revision(engine, current_revision(engine), head_revision())
        _register_spindle(engine, spindle)


def _migration_target(engine: Engine) -> Engine | str:
    """PostgreSQL: the URL (``upgrade`` opens and disposes an engine of its own, no watchdog on it); SQLite:
    the engine itself (an in-memory database exists only there; it has no statement timeout)."""
    if engine.dialect.name == "postgresql":
        return engine.url.render_as_string(hide_password=False)
    return engine


def _register_spindle(engine: Engine, spindle: SpindleSettings | None) -> None:
    from datetime import UTC
    from datetime import datetime as _dt

    from service.store.engine import DEFAULT_SPINDLE_ID, make_session_factory
    from service.store.repository import ensure_spindle, session_scope

    sid = spindle.id if spindle is not None else DEFAULT_SPINDLE_ID
    desc = spindle.description if spindle is not None else ""
    with session_scope(make_session_factory(engine, spindle_id=sid), "register the spindle") as session:
        ensure_spindle(session, sid, description=desc, now=_dt.now(UTC))


def _check_revision(engine: Engine, rev: str | None, head: str) -> None:
    if rev != head:
        missing = "has no chtc schema" if rev is None else f"schema is at revision {rev}"
        raise SchemaError(
            f"database reachable, but it {missing}; this version needs revision {head}: "
            "run once with --migrate (chtc run --migrate)"
        )


def _start_writer(
    session_factory: sessionmaker[Session],
    db: DatabaseSettings,
    *,
    clock: Callable[[], datetime] | None,
    watchdog: StatementWatchdog | None = None,
    on_write: Callable[[float], None] | None = None,
    heartbeat: Heartbeat | None = None,
) -> DbWriter:
    from service.store.writer import DbWriter, utc_now

    return DbWriter(
        session_factory,
        clock=clock or utc_now,
        batch_size=db.batch_size,
        buffer_max=db.buffer_max,
        retry_initial_s=db.retry_initial_s,
        retry_max_s=db.retry_max_s,
        watchdog=watchdog,
        heartbeat_s=db.heartbeat_s,
        heartbeat=heartbeat,
        stall_s=db.stall_s,
        downsample=True,
        on_write=on_write,
    ).start()


def _engine(
    db: DatabaseSettings, spindle_id: str, *, writer: bool = False
) -> tuple[Engine, sessionmaker[Session], StatementWatchdog]:
    """(engine, session factory, watchdog): one per use (the writer's, the API reads'), each its own pool."""
    from service.store.engine import make_session_factory

    engine, watchdog = _bare_engine(db, writer=writer)
    return engine, make_session_factory(engine, spindle_id=spindle_id), watchdog


def _bare_engine(db: DatabaseSettings, *, writer: bool = False) -> tuple[Engine, StatementWatchdog]:
    """``writer``: the writers' engine, without the pool's pre-ping (a write on a dead connection fails,
    the pool is invalidated and the writer retries, as for any outage): a ``SELECT 1`` before each write was
    a fifth of the writers' time at N = 50 (docs/design/fleet.md)."""
    from service.store.engine import create_db_engine
    from service.store.watchdog import StatementWatchdog

    statement_s = float(db.statement_timeout_s)
    engine = create_db_engine(
        db.url,
        echo=db.echo,
        connect_timeout_s=float(db.connect_timeout_s),
        statement_timeout_s=statement_s,
        pool_size=db.pool_size,
        max_overflow=db.max_overflow,
        transaction_pooling=db.transaction_pooling,
        pre_ping=not writer,
    )
    watchdog = StatementWatchdog(engine, abort_after_s=statement_s + 1.0).start()
    return engine, watchdog


def _safe_url(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


@dataclass(kw_only=True)
class SharedDatabase:
    """The engines (and their watchdogs) of one instance that hosts several spindles: one pool for the API's
    reads and one for the writers, shared by every spindle's ``Persistence`` (each keeps its own
    spindle-bound session factory, writer thread and read threads), and the writer engine's idle probe
    (``writer_heartbeat``: one ``SELECT 1`` answers every idle writer). The writers share the writer engine's
    watchdog, but what it aborts and each writer's ``busy_s`` are that writer's own (one spindle's stuck write
    degrades no other). Closed by its owner, after them."""

    engine: Engine
    read_watchdog: StatementWatchdog
    writer_engine: Engine
    writer_watchdog: StatementWatchdog
    writer_heartbeat: Heartbeat

    @classmethod
    def open(cls, db: DatabaseSettings) -> SharedDatabase:
        from service.store.writer import Heartbeat

        engine, watchdog = _bare_engine(db)
        w_engine, w_watchdog = _bare_engine(db, writer=True)
        return cls(
            engine=engine,
            read_watchdog=watchdog,
            writer_engine=w_engine,
            writer_watchdog=w_watchdog,
            writer_heartbeat=Heartbeat(),
        )

    def close(self) -> None:
        for watchdog in (self.writer_watchdog, self.read_watchdog):
            watchdog.close()
        self.engine.dispose()
        self.writer_engine.dispose()


def open_persistence(
    db: DatabaseSettings,
    *,
    migrate: bool,
    on_event: Callable[[str], None] | None = None,
    clock: Callable[[], datetime] | None = None,
    spindle: SpindleSettings | None = None,
    shared: SharedDatabase | None = None,
    retention: bool = True,
    log_time: bool = False,
) -> Persistence:
    """Engine + schema + restore + writer for ``settings.database``; never raises for a database outage.

    ``clock`` is the service's one clock (``service.host.runtime.ScaledClock`` in the demo): the writer
    stamps its
    outage events and ``last_ok_at`` with it, so database health ages are on the same time axis as the rest.
    ``log_time``: that clock replays a log (``Persistence.log_time``: retention ages by the stored samples).
    """
    from service.store.reads import DbReads

    say = on_event or (lambda _m: None)
    from service.store.engine import DEFAULT_SPINDLE_ID

    sid = spindle.id if spindle is not None else DEFAULT_SPINDLE_ID
    heartbeat = None if shared is None else shared.writer_heartbeat
    if shared is None:
        engine, factory, read_watchdog = _engine(db, sid)
        w_engine, w_factory, w_watchdog = _engine(db, sid, writer=True)
    else:
        from service.store.engine import make_session_factory

        engine, read_watchdog = shared.engine, shared.read_watchdog
        w_engine, w_watchdog = shared.writer_engine, shared.writer_watchdog
        factory = make_session_factory(engine, spindle_id=sid)
        w_factory = make_session_factory(w_engine, spindle_id=sid)
    sink = GateSink(max_held=db.buffer_max)
    try:
        _prepare_schema(engine, migrate, spindle, watchdog=read_watchdog)
        with read_watchdog.guard("restore"):  # a hung database cannot hold the start-up
            restored = restore(factory, on_problem=say)
        from_db = True
        sink.open(
            _start_writer(
                w_factory,
                db,
                clock=clock,
                watchdog=w_watchdog,
                on_write=sink.write_latency.observe,
                heartbeat=heartbeat,
            )
        )
    except Exception as err:  # unreachable or unmigrated: run on, buffer, retry in the background
        sink.last_error = _describe(err)
        restored, from_db = fallback_restored(), False
        # a warning, logged (stderr) once: also under `chtc demo --quiet`, which silences progress lines only
        log.warning(
            "db: not available at start-up (%s); buffering records and retrying; ids start at %d (clear of "
            "any stored row) unless it answers before the first condition",
            sink.last_error,
            restored.next_condition_id,
        )
    reads = DbReads(
        factory,
        threads=db.read_threads,
        timeout_s=db.read_timeout_s,
        watchdog=read_watchdog,
    )
    return Persistence(
        url=db.url,
        engine=engine,
        session_factory=factory,
        sink=sink,
        restored=restored,
        restored_from_db=from_db,
        settings=db,
        migrate=migrate,
        on_event=say,
        clock=clock,
        writer_engine=w_engine,
        writer_factory=w_factory,
        writer_watchdog=w_watchdog,
        reads=reads,
        read_watchdog=read_watchdog,
        spindle=spindle,
        owns_engines=shared is None,
        heartbeat=heartbeat,
        retention=retention,
        log_time=log_time,
    )


def _complete(h: tuple[float | None, ...]) -> tuple[float, ...] | None:
    """H1..H7 when every one is stored, else None (a row without H is no warm start)."""
    values = tuple(x for x in h if x is not None)
    return values if len(values) == len(h) else None
