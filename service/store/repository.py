"""Queries and writes on one ``Session`` (one session per job or request: use ``session_scope``).

Lookups by id raise ``RecordNotFoundError``; ``last_identification`` returns
None only with its documented meaning ("there is none"). SQLAlchemy errors inside ``session_scope`` are
translated once into ``DatabaseUnavailableError`` / ``RecordError``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import date, datetime
from itertools import groupby
from typing import Generic, TypeVar

from sqlalchemy import Connection, Engine, Table, delete, func, insert, select, update
from sqlalchemy import exc as sa_exc
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import InstrumentedAttribute, Session, joinedload, sessionmaker
from sqlalchemy.sql import Select

from service.contracts.calibration import Calibration
from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.mechanics import MechanicsCalibration
from service.contracts.probe import ProbeMeasurement
from service.contracts.records import (
    ConditionEnd,
    ConditionStart,
    DeviceEventData,
    IdentificationData,
    Record,
    SampleData,
    SampleMinuteData,
)
from service.contracts.reference import CompensationReference
from service.store.errors import RecordNotFoundError
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
from service.store.partitions import ensure_days, prepare_days, utc_day
from service.store.sqlerrors import translate

T = TypeVar("T")


@dataclass(frozen=True, kw_only=True)
class Page(Generic[T]):
    items: Sequence[T]  # newest first
    total: int  # rows matching the filter over all pages
    limit: int
    offset: int


@contextmanager
def session_scope(factory: sessionmaker[Session], what: str = "database access") -> Iterator[Session]:
    """One unit of work: commit on success, roll back on error; SQLAlchemy errors become typed errors."""
    session = factory()
    try:
        yield session
        session.commit()
    except sa_exc.SQLAlchemyError as err:
        session.rollback()
        raise translate(err, what) from err
    finally:
        session.close()


# --- writes ---------------------------------------------------------------------------------------
_TABLE_OF: dict[type, type] = {
    ConditionStart: Condition,
    IdentificationData: Identification,
    DeviceEventData: DeviceEvent,
    SampleData: SampleRow,
    Calibration: OffsetCalibrationRow,
    CompensationReference: CompensationReferenceRow,
    LiveCheckpoint: LiveStateRow,
    MechanicsCalibration: MechanicsCalibrationRow,
    ProbeMeasurement: ProbeMeasurementRow,
    SampleMinuteData: SampleMinuteRow,
}
# keyed by (spindle_id, t): a retried batch (the commit went through, its acknowledgement did not) is skipped
_IDEMPOTENT = (SampleData, SampleMinuteData)


def spindle_of(session: Session) -> str:
    """The spindle a session belongs to (``service.store.engine.make_session_factory``)."""
    return str(session.info["spindle_id"])


def ensure_spindle(session: Session, spindle_id: str, *, description: str = "", now: datetime) -> None:
    """Register ``spindle_id`` in ``spindles`` (every row refers to it); a new description replaces the
    stored one."""
    row = session.get(Spindle, spindle_id)
    if row is None:
        session.add(Spindle(id=spindle_id, description=description, created_at=now))
    elif description and row.description != description:
        row.description = description
    session.flush()


def write_records(session: Session, records: Sequence[Record]) -> None:
    """Write records stamped with the session's spindle, in a few statements whatever the batch's length:
    samples and minute means (rows of their own, keyed by time, referred to by nothing) one multi-row INSERT
    each, skipping rows already stored; the other records in order, runs of one kind one multi-row INSERT (or
    one UPDATE each for ends); of the live-state checkpoints only the newest, which replaces the stored one.
    An outage's backlog interleaves a checkpoint a minute with the samples: written run by run, its round
    trips outlasted the writer's stall limit and every retry was aborted (docs/design/persistence.md).
    """
    sid = spindle_of(session)
    keyed: dict[type, list[Record]] = {kind: [] for kind in _IDEMPOTENT}
    ordered: list[Record] = []
    newest: LiveCheckpoint | None = None
    for r in records:  # one pass: the keyed rows, the rest in order, the newest checkpoint
        if type(r) in keyed:
            keyed[type(r)].append(r)
        elif isinstance(r, LiveCheckpoint):
            newest = r
        else:
            ordered.append(r)
    days = {utc_day(r.t) for r in keyed[SampleData] if isinstance(r, SampleData)}
    if days:  # PostgreSQL: the days' partitions first, committed apart from the batch (never inside it)
        _prepare_partitions(session, days)
    for kind, kept in keyed.items():
        if kept:
            insert_ignore_rows(session, _TABLE_OF[kind], [_stamped(r, sid) for r in kept])
    for kind, group in groupby(ordered, key=type):
        run = list(group)
        if kind is ConditionEnd:
            for end in run:
                assert isinstance(end, ConditionEnd)
                _end_condition(session, end)
        elif kind is IdentificationData:
            rows = [_split_speed_map(session, r, sid) for r in run]  # type: ignore[arg-type]
            session.execute(insert(Identification), rows)
        else:
            session.execute(insert(_TABLE_OF[kind]), [_stamped(r, sid) for r in run])
    if newest is not None:  # one row: the newest checkpoint replaces the stored one
        session.execute(delete(LiveStateRow).where(LiveStateRow.spindle_id == sid))
        session.execute(insert(LiveStateRow), [_stamped(newest, sid)])


def _prepare_partitions(session: Session, days: set[date]) -> None:
    """``service.store.partitions.prepare_days`` on the session's engine; a session bound to a connection
    (the caller owns the transaction) makes them in it."""
    bind = session.get_bind()
    if isinstance(bind, Engine):
        prepare_days(bind, days)
    else:
        ensure_days(session.connection(), days)


def _stamped(record: Record, sid: str) -> dict[str, object]:
    return {**record.values(), "spindle_id": sid}  # type: ignore[union-attr]


def insert_ignore_rows(
    target: Session | Connection, model: type[Base], rows: Sequence[dict[str, object]]
) -> None:
    """``INSERT … ON CONFLICT DO NOTHING`` of ``rows`` (column dicts) on SQLite and PostgreSQL."""
    table = model.__table__
    ins = postgresql.insert if _dialect(target) == "postgresql" else sqlite.insert
    target.execute(ins(table).on_conflict_do_nothing(), list(rows))  # type: ignore[arg-type]


def _dialect(target: Session | Connection) -> str:
    return str(target.dialect.name if isinstance(target, Connection) else target.get_bind().dialect.name)


def _upsert(session: Session, table: Table, values: dict[str, object], keys: list[str]) -> None:
    dialect = _dialect(session)
    ins = (postgresql.insert if dialect == "postgresql" else sqlite.insert)(table).values(**values)
    changed = {k: v for k, v in values.items() if k not in keys}
    session.execute(ins.on_conflict_do_update(index_elements=keys, set_=changed))


COV_KEYS = ("cov_upper_b64", "cov")  # SpeedMap.to_json's covariance (now, earlier form)


def _split_speed_map(session: Session, record: IdentificationData, sid: str) -> dict[str, object]:
    """The identification row, its speed map stored without the covariance; a successful map fit's whole
    state (with the covariance, ~19 kB) replaces the spindle's row in ``speed_map_state``."""
    row = _stamped(record, sid)
    diag = row.get("diagnostics")
    stored = diag.get("speed_map") if isinstance(diag, dict) else None
    if not isinstance(stored, dict) or not any(k in stored for k in COV_KEYS):
        return row
    if record.outcome == "ok":
        state = {
            "spindle_id": sid,
            "identification_id": record.id,
            "fitted_at": _fitted_at(stored, record.finished_at),
            "state": stored,
        }
        _upsert(session, SpeedMapStateRow.__table__, state, ["spindle_id"])  # type: ignore[arg-type]
    light = {k: v for k, v in stored.items() if k not in COV_KEYS}
    return {**row, "diagnostics": {**diag, "speed_map": {**light, "covariance_in": "speed_map_state"}}}  # type: ignore[dict-item]


def _fitted_at(stored: dict[str, object], default: datetime) -> datetime:
    try:
        at = datetime.fromisoformat(str(stored["fitted_at"]))
    except (KeyError, ValueError):
        return default
    return at if at.tzinfo is not None else default


def _end_condition(session: Session, end: ConditionEnd) -> None:
    query = update(Condition).where(Condition.spindle_id == spindle_of(session), Condition.id == end.id)
    result = session.execute(query.values(ended_at=end.ended_at))
    if getattr(result, "rowcount", 1) == 0:
        raise RecordNotFoundError(f"conditions: no id {end.id} to end")


def add_condition(session: Session, record: ConditionStart) -> Condition:
    row = Condition(**record.values(), spindle_id=spindle_of(session))
    session.add(row)
    session.flush()
    return row


def end_condition(session: Session, record: ConditionEnd) -> None:
    _end_condition(session, record)


def add_identification(session: Session, record: IdentificationData) -> Identification:
    write_records(session, [record])
    return get_identification(session, record.id)


def add_device_event(session: Session, record: DeviceEventData) -> DeviceEvent:
    row = DeviceEvent(**record.values(), spindle_id=spindle_of(session))
    session.add(row)
    session.flush()
    return row


def add_samples(session: Session, records: Sequence[SampleData]) -> None:
    if records:
        write_records(session, records)


def add_offset_calibration(session: Session, record: Calibration) -> OffsetCalibrationRow:
    row = OffsetCalibrationRow(**record.values(), spindle_id=spindle_of(session))
    session.add(row)
    session.flush()
    return row


# --- reads ----------------------------------------------------------------------------------------
def get_condition(session: Session, condition_id: int) -> Condition:
    row = session.scalars(select(Condition).where(Condition.id == condition_id)).first()
    if row is None:
        raise RecordNotFoundError(f"conditions: no id {condition_id}")
    return row


def list_conditions(
    session: Session,
    *,
    since: datetime | None = None,
    until: datetime | None = None,
    limit: int = 50,
    offset: int = 0,
) -> Page[Condition]:
    """Conditions started in [since, until), newest first."""
    query = _time_filter(select(Condition), Condition.started_at, since, until)
    return _page(session, query.order_by(Condition.started_at.desc(), Condition.id.desc()), limit, offset)


def get_identification(session: Session, identification_id: int) -> Identification:
    query = select(Identification).where(Identification.id == identification_id)
    row = session.scalars(query.options(joinedload(Identification.condition))).first()
    if row is None:
        raise RecordNotFoundError(f"identifications: no id {identification_id}")
    return row


def list_identifications(
    session: Session,
    *,
    since: datetime | None = None,
    until: datetime | None = None,
    limit: int = 50,
    offset: int = 0,
    outcome: str | None = None,
    condition_id: int | None = None,
) -> Page[Identification]:
    """Identifications finished in [since, until), newest first, with their condition loaded."""
    query = _time_filter(select(Identification), Identification.finished_at, since, until)
    if outcome is not None:
        query = query.where(Identification.outcome == outcome)
    if condition_id is not None:
        query = query.where(Identification.condition_id == condition_id)
    query = query.options(joinedload(Identification.condition))
    order = (Identification.finished_at.desc(), Identification.id.desc())
    return _page(session, query.order_by(*order), limit, offset)


def last_identification(
    session: Session, *, outcome: str | None = "ok", condition_id: int | None = None
) -> Identification | None:
    """The newest identification (default: successful ones only); None if there is none."""
    page = list_identifications(session, limit=1, outcome=outcome, condition_id=condition_id)
    return page.items[0] if page.items else None


def last_served_identification(session: Session, *, method: str | None = None) -> Identification | None:
    """The successful identification served last: the highest id (ids grow in launch order across restarts,
    ``service.host.persistence.restore``), not the newest ``finished_at``: in the demo each run's simulated
    clock starts again at the wall clock, so a later run's results can carry earlier times. ``method``: only
    those of this method (e.g. the newest speed-map fit). None if there is none.
    """
    query = select(Identification).where(Identification.outcome == "ok")
    if method is not None:
        query = query.where(Identification.method == method)
    query = query.options(joinedload(Identification.condition)).order_by(Identification.id.desc()).limit(1)
    return session.scalars(query).first()


def latest_per_condition(session: Session, *, limit: int = 100) -> list[Identification]:
    """The newest successful identification of each of the ``limit`` most recent conditions, newest first.

    Seeds the scheduler's warm-start memory after a restart.
    """
    newest = (
        select(Identification.condition_id, func.max(Identification.finished_at).label("t"))
        .where(Identification.outcome == "ok")
        .group_by(Identification.condition_id)
        .subquery()
    )
    query = (
        select(Identification)
        .join(
            newest,
            (Identification.condition_id == newest.c.condition_id)
            & (Identification.finished_at == newest.c.t),
        )
        .where(Identification.outcome == "ok")
        .options(joinedload(Identification.condition))
        .order_by(Identification.finished_at.desc(), Identification.id.desc())
    )
    seen: set[int] = set()
    out: list[Identification] = []
    for row in session.scalars(query):
        if row.condition_id not in seen and len(out) < limit:
            seen.add(row.condition_id)
            out.append(row)
    return out


def max_ids(session: Session) -> tuple[int, int]:
    """(largest condition id, largest identification id), 0 for an empty table: where the service resumes."""
    cond = session.scalar(select(func.max(Condition.id))) or 0
    ident = session.scalar(select(func.max(Identification.id))) or 0
    return int(cond), int(ident)


def list_device_events(
    session: Session,
    *,
    since: datetime | None = None,
    until: datetime | None = None,
    device: str | None = None,
    limit: int = 100,
    offset: int = 0,
) -> Page[DeviceEvent]:
    """Device events at t in [since, until), newest first."""
    query = _time_filter(select(DeviceEvent), DeviceEvent.t, since, until)
    if device is not None:
        query = query.where(DeviceEvent.device == device)
    return _page(session, query.order_by(DeviceEvent.t.desc(), DeviceEvent.id.desc()), limit, offset)


def list_samples(
    session: Session, *, since: datetime | None = None, until: datetime | None = None, limit: int = 10_000
) -> list[SampleRow]:
    """Stored samples at t in [since, until), oldest first (for replay and plots)."""
    query = _time_filter(select(SampleRow), SampleRow.t, since, until)
    return list(session.scalars(query.order_by(SampleRow.t).limit(limit)))


def list_sample_minutes(
    session: Session, *, since: datetime | None = None, until: datetime | None = None, limit: int = 10_000
) -> list[SampleMinuteRow]:
    """Stored 1-minute means starting in [since, until), oldest first."""
    query = _time_filter(select(SampleMinuteRow), SampleMinuteRow.t, since, until)
    return list(session.scalars(query.order_by(SampleMinuteRow.t).limit(limit)))


def last_speed_map_state(session: Session) -> SpeedMapStateRow | None:
    """The spindle's newest speed-map state (with its covariance); None if no map was ever fitted."""
    return session.scalars(select(SpeedMapStateRow).limit(1)).first()


def last_compensation_reference(session: Session) -> CompensationReferenceRow | None:
    """The newest compensation zero (latest ``at``, then highest id); None if none was ever set."""
    query = select(CompensationReferenceRow).order_by(
        CompensationReferenceRow.at.desc(), CompensationReferenceRow.id.desc()
    )
    return session.scalars(query.limit(1)).first()


def last_mechanics_calibration(session: Session) -> MechanicsCalibrationRow | None:
    """The newest commissioning of the mechanics (latest ``at``, then highest id); None if none."""
    query = select(MechanicsCalibrationRow).order_by(
        MechanicsCalibrationRow.at.desc(), MechanicsCalibrationRow.id.desc()
    )
    return session.scalars(query.limit(1)).first()


def recent_probe_measurements(session: Session, limit: int = 1000) -> list[ProbeMeasurementRow]:
    """The newest ``limit`` probe readings, oldest first (by ``at``, then id)."""
    query = select(ProbeMeasurementRow).order_by(ProbeMeasurementRow.at.desc(), ProbeMeasurementRow.id.desc())
    return list(reversed(session.scalars(query.limit(limit)).all()))


def last_live_state(session: Session) -> LiveStateRow | None:
    """The live state's stored checkpoint (the newest, should a write have left two); None if none."""
    query = select(LiveStateRow).order_by(LiveStateRow.at.desc(), LiveStateRow.id.desc())
    return session.scalars(query.limit(1)).first()


def last_offset_calibration(session: Session) -> OffsetCalibrationRow | None:
    """The newest sensor offset baseline (latest ``t_to``, then highest id); None if none was ever taken."""
    query = select(OffsetCalibrationRow).order_by(
        OffsetCalibrationRow.t_to.desc(), OffsetCalibrationRow.id.desc()
    )
    return session.scalars(query.limit(1)).first()


def list_offset_calibrations(
    session: Session, *, limit: int = 50, offset: int = 0
) -> Page[OffsetCalibrationRow]:
    """Sensor offset baselines, newest first."""
    order = (OffsetCalibrationRow.t_to.desc(), OffsetCalibrationRow.id.desc())
    return _page(session, select(OffsetCalibrationRow).order_by(*order), limit, offset)


def count_rows(session: Session, model: type[Base]) -> int:
    return int(session.scalar(select(func.count()).select_from(model)) or 0)


def _time_filter(
    query: Select[T], column: InstrumentedAttribute[datetime], since: datetime | None, until: datetime | None
) -> Select[T]:
    if since is not None:
        query = query.where(column >= since)
    if until is not None:
        query = query.where(column < until)
    return query


def _page(session: Session, query: Select[T], limit: int, offset: int) -> Page[T]:
    if limit < 1 or offset < 0:
        raise ValueError(f"need limit >= 1 and offset >= 0, got limit={limit}, offset={offset}")
    total = session.scalar(select(func.count()).select_from(query.order_by(None).subquery())) or 0
    items = list(session.scalars(query.limit(limit).offset(offset)).unique())
    return Page(items=items, total=int(total), limit=limit, offset=offset)
