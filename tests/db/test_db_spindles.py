"""Many spindles in one database (issue 29): each sees only its own rows; retried sample batches; the speed
map's newest state in its own table; minute means from the writer."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.checkpoint import LiveCheckpoint
from service.contracts.records import (
    ConditionEnd,
    ConditionStart,
    DeviceEventData,
    SampleData,
)
from service.host.persistence import restore
from service.identify.speedmap import SpeedMap
from service.store import repository as repo
from service.store.models import (
    Condition,
    DeviceEvent,
    Identification,
    LiveStateRow,
    SampleMinuteRow,
    SampleRow,
    SpeedMapStateRow,
)
from service.store.writer import DbWriter
from tests.db.conftest import spindle_factory, wait_until
from tests.db.test_db_repository import ident

T0 = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)


def samples(n: int, *, base: float, start: datetime = T0, step_s: int = 10) -> list[SampleData]:
    return [
        SampleData(
            t=start + timedelta(seconds=step_s * i),
            temps_c=[base + 0.01 * i + 0.25 * (c % 3) for c in range(32)],
            ambient_c=22.0,
            speed_rpm=3000.0 + 10 * i,
            torque_nm=10.0,
            quality=["ok"] * 32,
        )
        for i in range(n)
    ]


def fill(factory: sessionmaker[Session], *, base: float, h1: float) -> None:
    """The same ids and times for every spindle: only the spindle id tells the rows apart."""
    records = [
        ConditionStart(id=1, started_at=T0, speed_rpm=3000.0, torque_nm=8.0, ambient_c=base),
        ConditionEnd(1, T0 + timedelta(minutes=30)),
        ConditionStart(
            id=2, started_at=T0 + timedelta(minutes=30), speed_rpm=4000.0, torque_nm=8.0, ambient_c=base
        ),
        ident(1, 1, T0 + timedelta(minutes=20), h=[h1, 46.0, 68.0, 46.0, 52.0, 70.0, 16.0]),
        DeviceEventData(t=T0, device="can", kind=f"gap-{base}"),
        LiveCheckpoint(
            t=T0.timestamp(),
            model_version="m",
            converged=True,
            inputs=(base, 1.0, 1.0),
            mean=np.zeros(2),
            cov=np.eye(2),
            cross=np.zeros((2, 9)),
            bias_s=np.zeros((2, 3)),
            bias_m=np.eye(2),
        ),
        *samples(30, base=base),
    ]
    with repo.session_scope(factory) as s:
        repo.write_records(s, records)


def test_two_spindles_never_see_each_others_rows(engine: sa.Engine) -> None:
    a, b = spindle_factory(engine, "cellA-01"), spindle_factory(engine, "cellB-02")
    fill(a, base=20.0, h1=81.0)
    fill(b, base=30.0, h1=91.0)
    for factory, base, h1 in ((a, 20.0, 81.0), (b, 30.0, 91.0)):
        with repo.session_scope(factory) as s:
            assert {
                m.__tablename__: repo.count_rows(s, m)
                for m in (Condition, Identification, DeviceEvent, SampleRow, LiveStateRow)
            } == {"conditions": 2, "identifications": 1, "device_events": 1, "samples": 30, "live_state": 1}
            assert repo.get_identification(s, 1).h[0] == h1
            assert repo.get_identification(s, 1).condition.ambient_c == base  # the join stays in the spindle
            assert repo.get_condition(s, 1).ended_at == T0 + timedelta(minutes=30)  # ended in its own spindle
            assert repo.get_condition(s, 2).ended_at is None
            page = repo.list_identifications(s, limit=10)
            assert page.total == 1 and [r.h[0] for r in page.items] == [h1]
            assert [r.h[0] for r in repo.latest_per_condition(s)] == [h1]
            assert repo.max_ids(s) == (2, 1)
            assert {r.temps_c[0] for r in repo.list_samples(s)} == {
                round(base + 0.01 * i, 2) for i in range(30)
            }
            assert [e.kind for e in repo.list_device_events(s).items] == [f"gap-{base}"]
            live = repo.last_live_state(s)
            assert live is not None and live.ambient_c == base
        got = restore(factory)
        assert got.last is not None and got.last.data.h is not None and got.last.data.h[0] == h1
        assert [c.ambient_c for c in got.conditions] == [base, base]
        assert got.next_condition_id == 3 and got.next_identification_id == 2
    with engine.connect() as conn:  # both are stored, side by side
        assert conn.execute(sa.text("SELECT count(*) FROM samples")).scalar() == 60
        assert conn.execute(sa.text("SELECT count(*) FROM live_state")).scalar() == 2


def test_a_retried_sample_batch_neither_fails_nor_duplicates(factory: sessionmaker[Session]) -> None:
    batch = samples(20, base=21.0)
    with repo.session_scope(factory) as s:
        repo.write_records(s, batch[:12])
    with repo.session_scope(factory) as s:  # the retry of a batch whose commit went through, plus new rows
        repo.write_records(s, batch)
    with repo.session_scope(factory) as s:
        rows = repo.list_samples(s)
    assert [r.t for r in rows] == [x.t for x in batch]
    assert rows[5].temps_c == [round(21.05 + 0.25 * (c % 3), 2) for c in range(32)]  # real[]: same decimals


def speed_map(seed: int, at: datetime) -> SpeedMap:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(56, 56))
    return SpeedMap(
        family="nodes",
        mean=rng.normal(size=56),
        cov=a @ a.T,
        visited_rpm=np.array([3000.0, 4000.0]),
        visited_s=np.array([600.0, 300.0]),
        fitted_at=at,
        identification_id=None,
        rmse_c=0.2,
    )


def test_the_speed_maps_newest_state_is_one_upserted_row_and_is_restored(
    factory: sessionmaker[Session],
) -> None:
    maps = [speed_map(i, T0 + timedelta(minutes=10 * i)) for i in range(3)]
    with repo.session_scope(factory) as s:
        repo.write_records(
            s, [ConditionStart(id=1, started_at=T0, speed_rpm=3e3, torque_nm=8.0, ambient_c=22.0)]
        )
        for i, m in enumerate(maps):
            diag = {"speed_map": m.to_json(), "at_bound": [False] * 7}
            repo.write_records(
                s, [ident(i + 1, 1, m.fitted_at + timedelta(seconds=5), method="speed-map", diagnostics=diag)]
            )
    with repo.session_scope(factory) as s:
        assert repo.count_rows(s, SpeedMapStateRow) == 1
        state = repo.last_speed_map_state(s)
        assert state is not None and state.identification_id == 3
        history = repo.get_identification(s, 1).diagnostics
        assert history is not None
        stored = history["speed_map"]
        assert (
            isinstance(stored, dict)
            and "cov_upper_b64" not in stored
            and stored["mean"] == maps[0].to_json()["mean"]
        )
    got = restore(factory).speed_map
    assert got is not None and got.restored and got.identification_id == 3
    np.testing.assert_array_equal(got.cov, maps[2].cov)
    np.testing.assert_array_equal(got.mean, maps[2].mean)


def test_the_writer_stores_minute_means_beside_the_samples(factory: sessionmaker[Session]) -> None:
    start = T0 + timedelta(seconds=5)
    data = samples(30, base=20.0, start=start)  # 5 minutes of 10-s samples: 08:00:05 .. 08:04:55
    with DbWriter(factory, downsample=True, retry_initial_s=0.02, retry_max_s=0.1) as w:
        w.submit_many(data)
        wait_until(lambda: w.status().written == 30, what="samples written")
    with repo.session_scope(factory) as s:
        minutes = repo.list_sample_minutes(s)
        assert repo.count_rows(s, SampleMinuteRow) == 5
    assert [m.t for m in minutes] == [T0 + timedelta(minutes=i) for i in range(5)]
    assert [m.n for m in minutes] == [6] * 5
    first = np.array([d.temps_c for d in data[:6]], dtype=float).mean(axis=0)
    # stored to 0.01 °C (revision 0008: centi-degrees), so within half of that
    np.testing.assert_allclose(np.array(minutes[0].temps_c, dtype=float), first, rtol=0, atol=0.005 + 1e-9)
    assert minutes[0].speed_max_rpm == 3050.0 and minutes[0].speed_rpm == 3025.0


def test_the_service_registers_its_spindle_stamps_its_rows_and_runs_retention(db_url: str) -> None:
    from service.host.persistence import open_persistence
    from service.settings import Settings, SpindleSettings

    db = Settings().database.model_copy(update={"url": db_url, "raw_days": 1, "minute_days": 2})
    spindle = SpindleSettings(id="cell2-s05", description="lathe 5")
    p = open_persistence(db, migrate=True, spindle=spindle, clock=lambda: T0 + timedelta(days=3))
    old = samples(12, base=20.0)  # 3 days before the clock: dropped, their minute means too
    assert all(p.sink.submit(x) for x in old)
    assert p.sink.submit(ConditionStart(id=1, started_at=T0, speed_rpm=1.0, torque_nm=1.0, ambient_c=1.0))
    p.sink.writer.flush(10.0)  # type: ignore[union-attr]
    report = p.retention_once()
    assert report.raw_cutoff == (T0 + timedelta(days=2)).date()
    assert p.close() is not None
    eng = sa.create_engine(db_url)
    try:
        with eng.connect() as conn:
            spindles = conn.execute(sa.text("SELECT id, description FROM spindles ORDER BY id")).all()
            assert [tuple(r) for r in spindles] == [("cell2-s05", "lathe 5")]
            assert conn.execute(sa.text("SELECT spindle_id FROM conditions")).scalars().all() == ["cell2-s05"]
            assert conn.execute(sa.text("SELECT count(*) FROM samples")).scalar() == 0
            minutes = conn.execute(sa.text("SELECT count(*) FROM samples_1min")).scalar()
    finally:
        eng.dispose()
    # 08:00's mean was written and dropped; 08:01's was still in progress, written at close
    assert minutes == 1 and (report.partitions_dropped or report.raw_rows_deleted == 12)
