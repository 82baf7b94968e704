"""Merge a one-spindle database (today's deployment: one database per spindle) into a shared one.

``merge(source, target, spindle_id=)``:

1. the source is brought to the newest revision in place (``0007`` stamps its rows with ``spindle_id``;
   back it up first, as before any upgrade); a source already at the head must hold that spindle's rows;
2. the target (migrated, see ``chtc db upgrade``) must not hold rows of ``spindle_id`` yet (a merge is not
   resumable: a failed one rolls back, whole);
3. every spindle-scoped table is copied in one target transaction, in key order (conditions before their
   identifications); service-assigned ids (conditions, identifications) are kept, database ids get new target
   ids; samples go in chunks of ``chunk`` rows, their days' partitions created first (PostgreSQL).

Minute means are copied as stored; raw days without them get them from the next retention pass before their
raw samples are dropped (``service.store.retention``). ``chtc db merge SRC --spindle ID`` runs it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import Connection, Engine, Select, Table, func, select

from service.store import migrate
from service.store.engine import create_db_engine
from service.store.errors import DatabaseError
from service.store.models import (
    Base,
    CompensationReferenceRow,
    Condition,
    DeviceEvent,
    Identification,
    LiveStateRow,
    MechanicsCalibrationRow,
    OffsetCalibrationRow,
    ProbeMeasurementRow,
    SampleMinuteRow,
    SampleRow,
    SpeedMapStateRow,
    Spindle,
)
from service.store.partitions import ensure_days, utc_day

__all__ = ["MergeError", "MergeReport", "merge"]

# copied in this order (foreign keys); the second item: the id is the database's (a new one in the target)
ORDER: tuple[tuple[type[Base], bool], ...] = (
    (Condition, False),
    (Identification, False),
    (DeviceEvent, True),
    (OffsetCalibrationRow, True),
    (CompensationReferenceRow, True),
    (LiveStateRow, True),
    (MechanicsCalibrationRow, True),
    (ProbeMeasurementRow, True),
    (SpeedMapStateRow, False),
    (SampleMinuteRow, False),
    (SampleRow, False),
)


class MergeError(DatabaseError, ValueError):
    """A merge refused before anything was written (the message says why)."""


@dataclass(frozen=True, kw_only=True)
class MergeReport:
    spindle_id: str
    rows: dict[str, int]  # table -> rows copied
    seconds: float


def merge(source: str | Engine, target: str | Engine, *, spindle_id: str, chunk: int = 5000) -> MergeReport:
    """See the module docstring; raises ``MergeError`` or the store's ``DatabaseError`` types."""
    import time

    t0 = time.perf_counter()
    src, own_src = (source, False) if isinstance(source, Engine) else (create_db_engine(source), True)
    dst, own_dst = (target, False) if isinstance(target, Engine) else (create_db_engine(target), True)
    try:
        migrate.upgrade(src, spindle_id=spindle_id)
        if migrate.current_revision(dst) != migrate.head_revision():
            raise MergeError(
                "the target database is not at the newest revision: run `chtc db upgrade` on it first"
            )
        rows: dict[str, int] = {}
        with src.connect() as s_conn, dst.begin() as d_conn:
            _check(s_conn, d_conn, spindle_id)
            _register(s_conn, d_conn, spindle_id)
            for model, db_id in ORDER:
                rows[model.__tablename__] = _copy(s_conn, d_conn, model, spindle_id, db_id=db_id, chunk=chunk)
        return MergeReport(spindle_id=spindle_id, rows=rows, seconds=time.perf_counter() - t0)
    finally:
        if own_src:
            src.dispose()
        if own_dst:
            dst.dispose()


def _table(model: type[Base]) -> Table:
    return cast(Table, model.__table__)


def _count(conn: Connection, model: type[Base], spindle_id: str) -> int:
    table = _table(model)
    return int(
        conn.execute(select(func.count()).select_from(table).where(table.c.spindle_id == spindle_id)).scalar()
        or 0
    )


def _check(src: Connection, dst: Connection, spindle_id: str) -> None:
    if sum(_count(src, m, spindle_id) for m, _ in ORDER) == 0:
        raise MergeError(
            f"the source holds no rows of spindle {spindle_id!r} (already migrated under another id?)"
        )
    taken = [m.__tablename__ for m, _ in ORDER if _count(dst, m, spindle_id)]
    if taken:
        raise MergeError(f"the target already holds rows of spindle {spindle_id!r} ({', '.join(taken)})")


def _register(src: Connection, dst: Connection, spindle_id: str) -> None:
    spindles = _table(Spindle)
    if dst.execute(select(spindles.c.id).where(spindles.c.id == spindle_id)).first() is not None:
        return
    row = src.execute(select(spindles).where(spindles.c.id == spindle_id)).mappings().first()
    values = (
        dict(row)
        if row is not None
        else {"id": spindle_id, "description": "", "created_at": datetime.now(UTC)}
    )
    dst.execute(spindles.insert(), [values])


def _copy(
    src: Connection, dst: Connection, model: type[Base], spindle_id: str, *, db_id: bool, chunk: int
) -> int:
    table = _table(model)
    cols = [c for c in table.columns if not (db_id and c.name == "id")]
    order = (
        [table.c.t] if "t" in table.c and model in (SampleRow, SampleMinuteRow) else list(table.primary_key)
    )
    query = select(*cols).where(table.c.spindle_id == spindle_id).order_by(*order)
    n = 0
    for batch in _chunks(src, query, chunk):
        if model is SampleRow:
            ensure_days(dst, {utc_day(cast(datetime, r["t"])) for r in batch})
        dst.execute(table.insert(), batch)
        n += len(batch)
    return n


def _chunks(conn: Connection, query: Select[Any], size: int) -> Iterator[list[dict[str, object]]]:
    result = conn.execution_options(yield_per=size).execute(query)
    for part in result.mappings().partitions(size):
        yield [dict(r) for r in part]
