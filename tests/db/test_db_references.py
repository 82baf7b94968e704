"""The compensation zero in a real database (SQLite, and PostgreSQL when configured): written as the
service's writer record, the newest restored by ``restore``, an unusable row reported and left."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from sqlalchemy import insert
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.reference import CompensationReference
from service.host.persistence import restore
from service.store.models import CompensationReferenceRow
from service.store.repository import session_scope, write_records

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def test_the_newest_zero_is_restored(factory: sessionmaker[Session]) -> None:
    assert restore(factory).reference is None
    old = CompensationReference(temperature_c=21.0, sd_c=0.0, at=AT, source="cli", set_by="alice")
    new = CompensationReference(
        temperature_c=22.25, sd_c=0.03, at=AT + timedelta(days=1), source="api", set_by="bob"
    )
    with session_scope(factory, "write") as s:
        write_records(s, [new, old])  # the order of writing is not it
    assert restore(factory).reference == new


def test_an_unusable_stored_zero_is_reported_and_none_is_used(factory: sessionmaker[Session]) -> None:
    with session_scope(factory, "write") as s:
        s.execute(
            insert(CompensationReferenceRow),
            [
                {
                    "at": AT,
                    "temperature_c": 21.0,
                    "sd_c": 0.0,
                    "source": "guessed",
                    "set_by": "x",
                    "spindle_id": "spindle1",
                }
            ],
        )
    said: list[str] = []
    assert restore(factory, on_problem=said.append).reference is None
    assert len(said) == 1 and "compensation_references row 1" in said[0] and "source" in said[0]
