"""The live state's checkpoint in a real database (SQLite, and PostgreSQL when configured): the writer's
record replaces the one row, ``restore`` reads it back bit for bit, a damaged row is reported and left."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import sqlalchemy as sa
from sqlalchemy import event, func, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.records import Record, SampleData
from service.host.persistence import restore
from service.store.models import LiveStateRow, SampleRow
from service.store.repository import session_scope, write_records

T0 = datetime(2026, 11, 27, 8, 0, tzinfo=UTC).timestamp()


def _checkpoint(t: float, seed: int, r: int = 5, n: int = 4) -> LiveCheckpoint:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(r, r))
    return LiveCheckpoint(
        t=t,
        model_version="abc123",
        converged=seed % 2 == 0,
        inputs=(21.5, 3000.0 + seed, 4.2),
        mean=rng.normal(size=r),
        cov=a @ a.T,
        cross=rng.normal(size=(r, 9)),
        bias_s=rng.normal(size=(r, n)),
        bias_m=a.T @ a,
    )


def test_the_newest_checkpoint_replaces_the_row_and_is_restored(factory: sessionmaker[Session]) -> None:
    assert restore(factory).live is None
    cps = [_checkpoint(T0 + 60.0 * i, i) for i in range(3)]
    with session_scope(factory, "write") as s:
        write_records(s, [cps[0]])
    with session_scope(factory, "write") as s:
        write_records(s, list(cps[1:]))
    with session_scope(factory, "count") as s:
        assert s.scalar(select(func.count()).select_from(LiveStateRow)) == 1
    got = restore(factory).live
    want = cps[-1]
    assert got is not None and got.t == want.t and got.inputs == want.inputs
    assert got.converged == want.converged and got.model_version == want.model_version
    for name in ("mean", "cov", "cross", "bias_s", "bias_m"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_a_damaged_checkpoint_is_reported_and_the_filter_starts_from_its_prior(
    factory: sessionmaker[Session],
) -> None:
    with session_scope(factory, "write") as s:
        write_records(s, [_checkpoint(T0, 1)])
        s.execute(update(LiveStateRow).values(payload=b"not an archive"))
    said: list[str] = []
    assert restore(factory, on_problem=said.append).live is None
    assert len(said) == 1 and "live_state row 1" in said[0] and "payload" in said[0]
    with session_scope(factory, "count") as s:
        assert s.scalar(select(func.count()).select_from(LiveStateRow)) == 1  # left for the next write


def test_a_backlog_of_samples_and_checkpoints_is_written_in_a_few_statements(
    engine: sa.Engine, factory: sessionmaker[Session]
) -> None:
    """An outage's backlog (a checkpoint each minute among 10-s samples) in one batch: every sample stored,
    the newest checkpoint only, in a number of statements that does not grow with the batch (written run by
    run it took ~3 per minute of backlog, and outlasted the writer's stall limit after a 15-s freeze)."""
    batch: list[Record] = []
    for i in range(300):
        at = datetime.fromtimestamp(T0, UTC) + timedelta(seconds=10 * i)
        temps, ok = [20.0] * 32, ["ok"] * 32
        batch.append(
            SampleData(t=at, temps_c=temps, ambient_c=22.0, speed_rpm=4000.0, torque_nm=10.0, quality=ok)
        )
        if i % 6 == 5:
            batch.append(_checkpoint(at.timestamp(), i))
    statements: list[str] = []
    event.listen(engine, "before_cursor_execute", lambda *a: statements.append(a[2]))
    with session_scope(factory, "write") as s:
        write_records(s, batch)
    assert len(statements) <= 12, statements
    with session_scope(factory, "count") as s:
        assert s.scalar(select(func.count()).select_from(SampleRow)) == 300
        assert s.scalar(select(func.count()).select_from(LiveStateRow)) == 1
    got = restore(factory).live
    assert got is not None and got.t == _checkpoint(T0 + 2990.0, 299).t and got.inputs[1] == 3000.0 + 299
