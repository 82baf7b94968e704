"""The commissioned mechanics in a real database (SQLite, and PostgreSQL when configured): written as the
service's writer record, the newest restored by ``restore`` with its posterior, source hashes and report, an
unusable row reported and left."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
from sqlalchemy import insert
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.mechanics import MechanicsCalibration
from service.host.persistence import restore
from service.store.models import MechanicsCalibrationRow
from service.store.repository import session_scope, write_records

AT = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)
SHA = {"temperatures": "a" * 64, "canlog": "b" * 64, "displacements": "c" * 64}


def _cal(at: datetime, s: float, by: str) -> MechanicsCalibration:
    cov = np.diag([0.04**2, 0.018**2, 0.049**2])
    cov[0, 1] = cov[1, 0] = -0.3 * 0.04 * 0.018
    return MechanicsCalibration(
        x=(s, 0.94, 1.03),
        cov=tuple(tuple(float(v) for v in row) for row in cov),
        at=at,
        set_by=by,
        source="cli",
        sources=dict(SHA),
        residual_rms_um=0.41,
        residual_max_um=2.3,
        explained=True,
        report={"verdict": "the model explains the test", "parameters": [{"name": "restraint", "value": s}]},
    )


def test_the_newest_commissioning_is_restored_with_its_posterior(factory: sessionmaker[Session]) -> None:
    assert restore(factory).mechanics is None
    old, new = _cal(AT, 0.3, "alice"), _cal(AT + timedelta(days=1), 0.64, "bob")
    with session_scope(factory, "write") as s:
        write_records(s, [new, old])  # the order of writing is not it
    got = restore(factory).mechanics
    assert got is not None
    assert got.x == new.x and got.set_by == "bob" and got.source == "cli" and got.at == new.at
    assert np.allclose(got.covariance, new.covariance, rtol=0, atol=1e-15)
    assert got.sources == SHA and got.explained and got.report == new.report
    assert got.residual_rms_um == 0.41 and got.residual_max_um == 2.3


def test_an_unusable_stored_commissioning_is_reported_and_none_is_used(
    factory: sessionmaker[Session],
) -> None:
    row = _cal(AT, 0.5, "x").values() | {"restraint": 1.7, "spindle_id": "spindle1"}
    with session_scope(factory, "write") as s:
        s.execute(insert(MechanicsCalibrationRow), [row])
    said: list[str] = []
    assert restore(factory, on_problem=said.append).mechanics is None
    assert len(said) == 1 and "mechanics_calibrations row 1" in said[0] and "restraint" in said[0]
