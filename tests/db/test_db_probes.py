"""Probe readings in a real database (SQLite, and PostgreSQL when configured): written as the service's
writer record, restored oldest first with their outcome and feature row, an unusable row reported and left."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from sqlalchemy import insert
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.probe import ProbeMeasurement
from service.host.persistence import restore
from service.store.models import ProbeMeasurementRow
from service.store.probes import probe_record
from service.store.repository import session_scope, write_records

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def _m(at: datetime, y: float, accepted: bool, *, step: bool = False) -> ProbeMeasurement:
    return ProbeMeasurement(
        at=at,
        axial_um=y,
        sd_um=0.8,
        features=((1.5, 7.25, -2.0), (0.5, -1.0, -2.75)),
        field_var_um2=0.04,
        predicted_um=y - 0.3,
        sigma_um=1.2,
        innovation_um=0.3 if accepted else 40.0,
        accepted=accepted,
        offset_step=step,
        set_by="plc",
        source="api",
    )


def test_readings_are_stored_and_restored_oldest_first(factory: sessionmaker[Session]) -> None:
    assert restore(factory).probes == ()
    first, flagged, last = (
        _m(AT, 4.5, True),
        _m(AT + timedelta(hours=1), 50.0, False),
        _m(AT + timedelta(hours=2), 5.0, True, step=True),  # absorbed as a step of the fixture offset
    )
    with session_scope(factory, "write") as s:
        write_records(s, [probe_record(m, AT + timedelta(hours=3)) for m in (last, first, flagged)])
    got = restore(factory).probes
    assert [m.at for m in got] == [first.at, flagged.at, last.at]
    assert [m.accepted for m in got] == [True, False, True]
    assert [m.offset_step for m in got] == [False, False, True]  # the replay takes the stored decision
    assert all(m.id is not None for m in got)
    for a, b in zip(got, (first, flagged, last), strict=True):
        assert a.features == b.features and a.axial_um == b.axial_um and a.sd_um == b.sd_um
        assert a.innovation_um == b.innovation_um and a.sigma_um == b.sigma_um and a.set_by == "plc"


def test_an_unusable_stored_reading_is_reported_and_none_are_replayed(factory: sessionmaker[Session]) -> None:
    row = probe_record(_m(AT, 1.0, True), AT).values() | {"features": [1.0, 2.0], "spindle_id": "spindle1"}
    with session_scope(factory, "write") as s:
        s.execute(insert(ProbeMeasurementRow), [row])
    said: list[str] = []
    assert restore(factory, on_problem=said.append).probes == ()
    assert len(said) == 1 and "probe_measurements row 1" in said[0] and "features" in said[0]
