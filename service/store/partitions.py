"""Daily partitions of ``samples`` on PostgreSQL (declarative range partitioning on ``t``, bounds in UTC).

A partition is ``samples_pYYYYMMDD`` holding ``[day 00:00 UTC, next day 00:00 UTC)``. What makes them:

- the writer, for the days of each batch it has not seen yet and the day after each (``prepare_days``),
  before the batch, in a short transaction of its own with a ``lock_timeout`` (issue 41.1): never inside a
  data batch, whose transaction a frozen link can leave open on the server for long (an orphaned session)
  holding every lock it took;
- the retention pass (``service.store.retention``), ``PREMAKE_DAYS`` ahead, so the writer rarely has to.

How (``ensure_days``): ``CREATE TABLE … (LIKE samples INCLUDING ALL)``, then ``ALTER TABLE samples ATTACH
PARTITION``, serialized by an advisory lock so concurrent spindles' writers do not race. Attaching takes a
``SHARE UPDATE EXCLUSIVE`` lock on ``samples``, which inserts do not wait for (``CREATE TABLE … PARTITION
OF`` takes ``ACCESS EXCLUSIVE``: every spindle's inserts would queue behind it). ``LOCK_TIMEOUT_MS`` bounds
every wait for a lock here (and in the retention pass): a DDL statement queued behind a stuck transaction
would make every later insert queue behind it; it gives up instead and is tried again (the writer buffers).

What drops them: the retention pass (``drop_before``), whole days older than ``database.raw_days``
(``DROP TABLE`` of the partition: immediate, and the space is freed, unlike a ``DELETE``).

What compacts them: the retention pass (``compact_day``) rebuilds a closed day's key index once, packed full.
Many spindles writing at once each insert in the middle of the ``(spindle_id, t)`` index, whose pages then
split half full: measured 0.60 MB a spindle-day instead of 0.32 MB packed (docs/design/persistence.md,
"Storage per spindle-day").

pg_partman (Debian ``postgresql-15-partman``) would do the same creation and dropping; it is not used: its
retention drops a partition without the minute-means backfill the pass does first, its configuration is
database-wide (one ``part_config`` row per parent table) and needs superuser rights to install, and it needs
a scheduler of its own (its background worker or cron). These ~80 lines, run by the service, need none.
SQLite has no partitions; everything here is a no-op there.
"""

from __future__ import annotations

import re
import weakref
from collections.abc import Iterable
from datetime import UTC, date, datetime, timedelta

from sqlalchemy import Connection, Engine, text

__all__ = [
    "COMPACTED",
    "PREFIX",
    "compact_day",
    "day_bounds",
    "drop_before",
    "ensure_days",
    "list_partitions",
    "partition_name",
    "prepare_days",
    "schema_lock",
    "short_lock_waits",
]

PREFIX = "samples_p"
PREMAKE_DAYS = 3
LOCK_TIMEOUT_MS = 2000  # partition DDL and the retention pass: the longest wait for a lock, ms
_NAME = re.compile(r"^samples_p(\d{8})$")
_LOCK = 0x43485443  # advisory lock key: partition DDL of this schema, one at a time ("CHTC"; schema_lock)
COMPACTED = "chtc: compacted"  # the comment on a closed day's rebuilt index (done once)
_known: weakref.WeakKeyDictionary[Engine, set[date]] = weakref.WeakKeyDictionary()


def partition_name(day: date) -> str:
    return f"{PREFIX}{day:%Y%m%d}"


def day_bounds(day: date) -> tuple[datetime, datetime]:
    lo = datetime(day.year, day.month, day.day, tzinfo=UTC)
    return lo, lo + timedelta(days=1)


def utc_day(t: datetime) -> date:
    return t.astimezone(UTC).date()


def partitioned(conn: Connection) -> bool:
    return conn.dialect.name == "postgresql"


def short_lock_waits(conn: Connection, ms: int = LOCK_TIMEOUT_MS) -> None:
    """PostgreSQL: this transaction waits at most ``ms`` for any lock (``SET LOCAL``: it ends with it)."""
    if partitioned(conn):
        conn.exec_driver_sql(f"SET LOCAL lock_timeout = {int(ms)}")


def schema_lock(conn: Connection, key: int) -> None:
    """``pg_advisory_xact_lock`` of ``key`` in the current schema: advisory locks are database-wide, and the
    services of another schema of the database (another plant, a test) have partitions of their own."""
    conn.execute(text("SELECT pg_advisory_xact_lock(:k, hashtext(current_schema()))"), {"k": key})


def prepare_days(engine: Engine, days: Iterable[date]) -> list[str]:
    """The partitions of ``days`` (needed now) and of the day after each (ahead of need), in a transaction
    of their own (committed on return; ``LOCK_TIMEOUT_MS``); the names created. A day known to this engine
    costs nothing, one that exists a catalog read. The days ahead are made only if the advisory lock is free
    at once: a partition-making transaction elsewhere (another spindle's, or one its lost connection left
    open on the server) never holds up a batch whose own days exist. Raises SQLAlchemy's errors (a needed
    day's lock not granted in time: ``OperationalError``, transient)."""
    if engine.dialect.name != "postgresql":
        return []
    known = _known.setdefault(engine, set())
    needed = set(days) - known
    ahead = {d + timedelta(days=1) for d in days} - known - needed
    if not needed and not ahead:
        return []
    with engine.begin() as conn:
        short_lock_waits(conn)
        existing = {d for _, d in list_partitions(conn)}
        must, may = sorted(needed - existing), sorted(ahead - existing)
        if must:
            schema_lock(conn, _LOCK)
            locked = True
        else:
            locked = bool(may) and _try_schema_lock(conn, _LOCK)
        created = _create_missing(conn, must + may) if locked else []
    known.update((needed | ahead) & existing)
    if locked:
        known.update(must + may)  # committed
    return created


def ensure_days(conn: Connection, days: Iterable[date]) -> list[str]:
    """Create the partitions of ``days`` that do not exist yet (PostgreSQL), in the caller's transaction
    (see the module docstring); the names created."""
    if not partitioned(conn):
        return []
    known = _known.setdefault(conn.engine, set())
    wanted = sorted(set(days) - known)
    if not wanted:
        return []
    schema_lock(conn, _LOCK)
    created = _create_missing(conn, wanted)
    # a new one is known once committed (seen next time)
    known.update(d for d in wanted if partition_name(d) not in created)
    return created


def _try_schema_lock(conn: Connection, key: int) -> bool:
    query = text("SELECT pg_try_advisory_xact_lock(:k, hashtext(current_schema()))")
    return bool(conn.execute(query, {"k": key}).scalar())


def _create_missing(conn: Connection, days: list[date]) -> list[str]:
    """Under the advisory lock: create the partitions of ``days`` not there; the names created."""
    existing = {d for _, d in list_partitions(conn)}
    created = []
    for day in days:
        if day not in existing:
            lo, hi = day_bounds(day)
            name = partition_name(day)
            conn.execute(text(f'CREATE TABLE "{name}" (LIKE samples INCLUDING ALL)'))
            conn.execute(
                text(
                    f'ALTER TABLE samples ATTACH PARTITION "{name}" '
                    f"FOR VALUES FROM ('{lo.isoformat()}') TO ('{hi.isoformat()}')"
                )
            )
            created.append(name)
    return created


def list_partitions(conn: Connection) -> list[tuple[str, date]]:
    """(name, day) of the partitions of ``samples`` in the current schema, oldest first."""
    if not partitioned(conn):
        return []
    rows = conn.execute(
        text(
            "SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid "
            "WHERE i.inhparent = 'samples'::regclass"
        )
    ).scalars()
    out = []
    for name in rows:
        m = _NAME.match(name)
        if m:
            out.append((name, datetime.strptime(m.group(1), "%Y%m%d").date()))
    return sorted(out, key=lambda p: p[1])


def drop_before(conn: Connection, cutoff: date) -> list[str]:
    """Drop the partitions of the days before ``cutoff`` (whole days only); the names dropped."""
    if not partitioned(conn):
        return []
    schema_lock(conn, _LOCK)
    dropped = []
    for name, day in list_partitions(conn):
        if day < cutoff:
            conn.execute(text(f'DROP TABLE "{name}"'))
            dropped.append(name)
    known = _known.get(conn.engine)
    if known is not None:
        known.difference_update(d for d in set(known) if d < cutoff)
    return dropped


def compact_day(conn: Connection, day: date) -> bool:
    """Rebuild the indexes of ``day``'s partition packed full (``fillfactor`` 100, ``REINDEX``) unless done
    already (the ``COMPACTED`` comment); True if rebuilt. For a closed day: its few late inserts wait for the
    rebuild (it locks the partition against writes while it runs, ~60 ms per 86 400 rows measured) and split
    the full pages they land in. No-op on SQLite and for a day without a partition."""
    if not partitioned(conn):
        return False
    rows = conn.execute(
        text(
            "SELECT c.relname, obj_description(c.oid, 'pg_class') FROM pg_index x "
            "JOIN pg_class c ON c.oid = x.indexrelid WHERE x.indrelid = to_regclass(:p)"
        ),
        {"p": f'"{partition_name(day)}"'},
    ).all()
    todo = [str(name) for name, note in rows if note != COMPACTED]
    for name in todo:
        conn.execute(text(f'ALTER INDEX "{name}" SET (fillfactor = 100)'))
        conn.execute(text(f'REINDEX INDEX "{name}"'))
        conn.execute(text(f"COMMENT ON INDEX \"{name}\" IS '{COMPACTED}'"))
    return bool(todo)
