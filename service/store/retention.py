"""Retention: raw samples kept ``raw_days``, their 1-minute means ``minute_days``, then dropped.

``retention_pass(engine, now=, raw_days=, minute_days=)`` runs over the whole database (every spindle: the
partitions are shared), in one transaction:

1. **backfill**: a day about to lose its raw samples whose spindle has no minute means in that day (rows
   stored before revision ``0007``, a merged database) gets them computed from the raw rows first
   (``service.store.downsample``); in steady state the writer has written them already and this is two index
   probes per spindle and day;
2. **raw samples** older than ``raw_days`` (whole UTC days before ``today - raw_days``): PostgreSQL drops
   their daily partitions (``service.store.partitions``; immediate, space freed); SQLite deletes the rows;
3. **minute means** older than ``minute_days``: deleted (a small table: 1440 rows per spindle-day);
4. PostgreSQL: the next ``PREMAKE_DAYS`` days' partitions are created;
5. PostgreSQL, after that transaction: the closed days still kept whose key index was not rebuilt yet are
   compacted (``partitions.compact_day``), newest first, at most ``compact_per_pass`` (2) a pass, each in its
   own short transaction (timed apart: ``compact_seconds``; ``seconds`` is steps 1–4). A failure (say, a
   partition another role owns: ``REINDEX`` needs its owner) is logged and ends the step; it is never fatal.

Identifications, conditions, calibrations, references, probe readings and device events are kept.
``0`` days keeps for ever. What runs it: the service, every ``database.retention_every_s`` (a day) of wall
time (``service.host.persistence``), and ``chtc db retention`` on demand. Concurrent passes (many
spindles' services) are serialized by an advisory lock on PostgreSQL and harmless anyway (idempotent).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import date, datetime, timedelta
from types import SimpleNamespace

from sqlalchemy import Connection, Engine, delete, func, select
from sqlalchemy.exc import DBAPIError

from service.store.downsample import minute_means
from service.store.models import SampleMinuteRow, SampleRow, Spindle
from service.store.partitions import (
    PREMAKE_DAYS,
    compact_day,
    day_bounds,
    drop_before,
    ensure_days,
    list_partitions,
    partition_name,
    schema_lock,
    short_lock_waits,
    utc_day,
)

__all__ = ["RetentionReport", "backfill_minutes", "retention_pass"]

log = logging.getLogger(__name__)
_LOCK = 0x43485452  # advisory lock key: one retention pass at a time in a schema ("CHTR"; schema_lock)
COMPACT_PER_PASS = 2  # closed days' indexes rebuilt a pass (yesterday, and one of a backlog)


@dataclass(frozen=True, kw_only=True)
class RetentionReport:
    raw_cutoff: date | None  # raw samples before this UTC day are gone (None: kept for ever)
    minute_cutoff: date | None
    partitions_dropped: tuple[str, ...]
    partitions_created: tuple[str, ...]
    raw_rows_deleted: int  # SQLite (PostgreSQL drops partitions: not counted)
    minute_rows_deleted: int
    minutes_backfilled: int
    seconds: float  # steps 1-4
    partitions_compacted: tuple[str, ...] = ()  # PostgreSQL: closed days' key indexes rebuilt packed
    compact_seconds: float = 0.0


def retention_pass(
    engine: Engine,
    *,
    now: datetime,
    raw_days: int,
    minute_days: int,
    premake_days: int = PREMAKE_DAYS,
    compact_per_pass: int = COMPACT_PER_PASS,
) -> RetentionReport:
    """One pass over the database (see the module docstring); ``now`` aware UTC."""
    t0 = time.perf_counter()
    today = utc_day(now)
    raw_cut = today - timedelta(days=raw_days) if raw_days > 0 else None
    min_cut = today - timedelta(days=minute_days) if minute_days > 0 else None
    dropped: list[str] = []
    raw_deleted = min_deleted = backfilled = 0
    with engine.begin() as conn:
        short_lock_waits(conn)  # a DROP queued behind a stuck writer would make every insert queue behind it
        if conn.dialect.name == "postgresql":
            schema_lock(conn, _LOCK)
        if raw_cut is not None:
            backfilled = _backfill_before(conn, raw_cut, keep_from=min_cut)
            if conn.dialect.name == "postgresql":
                dropped = drop_before(conn, raw_cut)
            else:
                lo, _ = day_bounds(raw_cut)
                raw_deleted = conn.execute(delete(SampleRow).where(SampleRow.t < lo)).rowcount
        if min_cut is not None:
            lo, _ = day_bounds(min_cut)
            min_deleted = conn.execute(delete(SampleMinuteRow).where(SampleMinuteRow.t < lo)).rowcount
        created = ensure_days(conn, [today + timedelta(days=i) for i in range(premake_days + 1)])
    seconds = time.perf_counter() - t0
    compacted = _compact_closed(engine, today, raw_cut, compact_per_pass)
    return RetentionReport(
        raw_cutoff=raw_cut,
        minute_cutoff=min_cut,
        partitions_dropped=tuple(dropped),
        partitions_created=tuple(created),
        raw_rows_deleted=int(raw_deleted or 0),
        minute_rows_deleted=int(min_deleted or 0),
        minutes_backfilled=backfilled,
        seconds=seconds,
        partitions_compacted=tuple(compacted),
        compact_seconds=time.perf_counter() - t0 - seconds,
    )


def _compact_closed(engine: Engine, today: date, raw_cut: date | None, limit: int) -> list[str]:
    """Step 5: the closed, kept days' partitions not compacted yet, newest first, at most ``limit``."""
    if engine.dialect.name != "postgresql" or limit < 1:
        return []
    with engine.connect() as conn:
        days = sorted(
            (d for _, d in list_partitions(conn) if d < today and (raw_cut is None or d >= raw_cut)),
            reverse=True,
        )
    done: list[str] = []
    for day in days:
        if len(done) >= limit:
            break
        try:
            with engine.begin() as conn:
                short_lock_waits(conn)
                schema_lock(conn, _LOCK)
                if compact_day(conn, day):
                    done.append(partition_name(day))
        except DBAPIError as err:  # e.g. a partition another role owns: storage only, never fatal
            log.warning("retention: compacting %s failed, left as is: %s", partition_name(day), err.orig)
            break
    return done


def _raw_days_before(conn: Connection, cutoff: date) -> list[date]:
    """The UTC days before ``cutoff`` that still hold raw samples."""
    if conn.dialect.name == "postgresql":
        return [d for _, d in list_partitions(conn) if d < cutoff]
    lo, _ = day_bounds(cutoff)
    first = conn.execute(select(func.min(SampleRow.t)).where(SampleRow.t < lo)).scalar()
    if first is None:
        return []
    start = utc_day(first)
    return [start + timedelta(days=i) for i in range((cutoff - start).days)]


def _backfill_before(conn: Connection, cutoff: date, *, keep_from: date | None) -> int:
    """Minute means for the spindle-days before ``cutoff`` that have raw samples and no means (only the days
    whose means are kept: on or after ``keep_from``)."""
    n = 0
    for day in _raw_days_before(conn, cutoff):
        if keep_from is not None and day < keep_from:
            continue
        lo, hi = day_bounds(day)
        for sid in _without_minutes(conn, lo, hi):  # steady state: none (the writer made them)
            if _has(conn, SampleRow, sid, lo, hi):
                n += backfill_minutes(conn, sid, lo, hi)
    return n


def _without_minutes(conn: Connection, lo: datetime, hi: datetime) -> list[str]:
    """The spindles with no minute means in [lo, hi): one statement, an index probe per spindle."""
    m = SampleMinuteRow
    has = select(m.t).where(m.spindle_id == Spindle.id, m.t >= lo, m.t < hi).exists()
    return list(conn.execute(select(Spindle.id).where(~has)).scalars())


def _has(
    conn: Connection, model: type[SampleRow] | type[SampleMinuteRow], sid: str, lo: datetime, hi: datetime
) -> bool:
    query = select(model.t).where(model.spindle_id == sid, model.t >= lo, model.t < hi).limit(1)
    return conn.execute(query).first() is not None


def backfill_minutes(conn: Connection, spindle_id: str, since: datetime, until: datetime) -> int:
    """Compute and store (skipping minutes already stored) the minute means of ``spindle_id``'s raw samples
    in ``[since, until)``; the number of minutes computed."""
    from service.store.repository import insert_ignore_rows

    rows = conn.execute(
        select(SampleRow.__table__)
        .where(SampleRow.spindle_id == spindle_id, SampleRow.t >= since, SampleRow.t < until)
        .order_by(SampleRow.t)
    ).mappings()  # (a Row's ``.t`` is SQLAlchemy's own attribute, not the column)
    means = minute_means(SimpleNamespace(**r) for r in rows)  # type: ignore[misc]
    if means:
        insert_ignore_rows(conn, SampleMinuteRow, [{**m.values(), "spindle_id": spindle_id} for m in means])
    return len(means)
