"""Retention (raw samples N days, minute means M days; PostgreSQL drops partitions), storage flat after N
days, and the merge of two one-spindle databases into a shared one."""

from __future__ import annotations

from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from service.commands.db import main as db_main
from service.contracts.records import ConditionStart, SampleData
from service.host.persistence import restore
from service.store import migrate
from service.store import repository as repo
from service.store.downsample import minute_means
from service.store.engine import create_db_engine, make_session_factory
from service.store.merge import MergeError, merge
from service.store.models import Identification, SampleMinuteRow, SampleRow
from service.store.partitions import list_partitions, partition_name
from service.store.retention import retention_pass
from tests.db.conftest import spindle_factory
from tests.db.test_db_migration_0007 import OLD_TABLES, _rows
from tests.db.test_db_repository import ident

TODAY = date(2026, 5, 20)
NOW = datetime(2026, 5, 20, 12, 0, tzinfo=UTC)


def day_samples(day: date, n: int = 12) -> list[SampleData]:
    """``n`` samples 2 min apart from 08:00 UTC of ``day`` (each its own minute)."""
    t0 = datetime(day.year, day.month, day.day, 8, tzinfo=UTC)
    return [
        SampleData(
            t=t0 + timedelta(minutes=2 * i),
            temps_c=[20.0 + i] * 4,
            ambient_c=22.0,
            speed_rpm=3e3,
            torque_nm=1.0,
            quality=["ok"] * 4,
        )
        for i in range(n)
    ]


def store_days(factory: sessionmaker[Session], days: list[date], *, with_minutes: bool) -> None:
    with repo.session_scope(factory) as s:
        for d in days:
            data = day_samples(d)
            repo.write_records(s, data + (minute_means(data) if with_minutes else []))


def days_of(
    factory: sessionmaker[Session], model: type[SampleRow] | type[SampleMinuteRow]
) -> dict[date, int]:
    with repo.session_scope(factory) as s:
        rows = s.scalars(sa.select(model.t)).all()
    out: dict[date, int] = {}
    for t in rows:
        out[t.date()] = out.get(t.date(), 0) + 1
    return out


def test_retention_keeps_the_right_rows_and_drops_whole_days(engine: sa.Engine) -> None:
    a, b = spindle_factory(engine, "a"), spindle_factory(engine, "b")
    days = [TODAY - timedelta(days=k) for k in range(6, -1, -1)]  # 6 days ago .. today
    store_days(a, days, with_minutes=True)  # as the writer stores them
    store_days(b, days, with_minutes=False)  # stored before the minute means existed: backfilled
    with repo.session_scope(a) as s:
        repo.write_records(
            s,
            [
                ConditionStart(
                    id=1, started_at=NOW - timedelta(days=30), speed_rpm=1.0, torque_nm=1.0, ambient_c=1.0
                ),
                ident(1, 1, NOW - timedelta(days=30)),
            ],
        )
    report = retention_pass(engine, now=NOW, raw_days=2, minute_days=4)
    raw_kept = {TODAY - timedelta(days=k): 12 for k in (2, 1, 0)}
    for f in (a, b):
        assert days_of(f, SampleRow) == raw_kept
        minutes = days_of(f, SampleMinuteRow)
        # minute means of days 4 and 3 ago kept (b's computed from the raw rows before they went)
        assert {d: minutes[d] for d in minutes if d < TODAY - timedelta(days=2)} == {
            TODAY - timedelta(days=4): 12,
            TODAY - timedelta(days=3): 12,
        }
    with repo.session_scope(a) as s:
        assert repo.count_rows(s, Identification) == 1  # identifications kept, however old
    assert report.minutes_backfilled == 24  # b: days 4 and 3 ago (6 and 5 ago are not kept: not computed)
    assert report.minute_rows_deleted == 2 * 12  # a's days 6 and 5 ago
    if engine.dialect.name == "postgresql":
        assert report.partitions_dropped == tuple(
            partition_name(TODAY - timedelta(days=k)) for k in (6, 5, 4, 3)
        )
        with engine.connect() as conn:
            assert [d for _, d in list_partitions(conn)] == [TODAY + timedelta(days=k) for k in range(-2, 4)]
    else:
        assert report.raw_rows_deleted == 2 * 4 * 12
    again = retention_pass(engine, now=NOW, raw_days=2, minute_days=4)  # idempotent
    assert (again.partitions_dropped, again.raw_rows_deleted, again.minutes_backfilled) == ((), 0, 0)


def test_storage_is_flat_after_n_days(factory: sessionmaker[Session], engine: sa.Engine) -> None:
    raw_rows = []
    for k in range(8):
        day = TODAY + timedelta(days=k)
        store_days(factory, [day], with_minutes=True)
        retention_pass(
            engine, now=datetime(day.year, day.month, day.day, 23, tzinfo=UTC), raw_days=3, minute_days=5
        )
        raw_rows.append(sum(days_of(factory, SampleRow).values()))
    assert raw_rows == [12, 24, 36, 48, 48, 48, 48, 48]  # today and the 3 days before


def _one_spindle_db(path: Path) -> str:
    url = f"sqlite:///{path}"
    eng = create_db_engine(url)
    migrate.upgrade(eng, "0006")
    with eng.begin() as conn:
        for name, n in OLD_TABLES.items():
            _rows(conn, name, n)
    eng.dispose()
    return url


def test_two_one_spindle_databases_merge_into_a_shared_one(db_url: str, tmp_path: Path) -> None:
    sources = {sid: _one_spindle_db(tmp_path / f"{sid}.db") for sid in ("s1", "s2")}  # the same ids in both
    migrate.upgrade(db_url)
    for sid, url in sources.items():
        report = merge(url, db_url, spindle_id=sid)
        assert {k: v for k, v in report.rows.items() if k in OLD_TABLES} == OLD_TABLES
    with pytest.raises(MergeError, match="already holds rows of spindle 's1'"):
        merge(sources["s1"], db_url, spindle_id="s1")
    eng = create_db_engine(db_url)
    try:
        with eng.connect() as conn:
            for name, n in OLD_TABLES.items():
                got = conn.execute(
                    sa.text(f"SELECT spindle_id, count(*) FROM {name} GROUP BY spindle_id ORDER BY 1")
                )
                assert [tuple(r) for r in got] == [("s1", n), ("s2", n)], name
        for sid in sources:
            got = restore(make_session_factory(eng, spindle_id=sid))
            assert got.next_identification_id == 5 and got.speed_map is None  # the fake map is no real one
    finally:
        eng.dispose()


def test_chtc_db_retention_and_merge_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    target = f"sqlite:///{tmp_path}/shared.db"
    source = _one_spindle_db(tmp_path / "old.db")
    migrate.upgrade(target)
    ns = argparse.Namespace(config=None, url=target, action="merge", source=source, spindle="cell1-s3")
    assert db_main(ns) == 0
    assert "merged" in capsys.readouterr().out
    ns = argparse.Namespace(config=None, url=target, action="retention", raw_days=1, minute_days=2)
    assert db_main(ns) == 0
    out = capsys.readouterr().out
    # the source's samples are from 2026-03-01/02: long gone after 1 day (their minutes after 2)
    assert "240 raw and 0 minute rows deleted, 0 minutes backfilled" in out


def test_a_closed_days_key_index_written_by_many_spindles_is_compacted_once(engine: sa.Engine) -> None:
    """Ten spindles write the same 2 h of 32-channel samples a minute each in turn (as their writers do): each
    spindle's key range grows in the middle of the index, whose pages split half full (PostgreSQL packs them
    only when the heap rows are adjacent, i.e. few spindles with small rows); the next day's pass rebuilds
    that index packed, once, keeping every row; a late batch still goes in. SQLite: nothing to compact."""
    ids = [f"cell1-s{k:02d}" for k in range(10)]  # ids of realistic length (the split depends on it)
    factories = [spindle_factory(engine, sid) for sid in ids]
    day = TODAY - timedelta(days=1)
    t0 = datetime(day.year, day.month, day.day, 8, tzinfo=UTC)
    data = [
        SampleData(
            t=t0 + timedelta(seconds=10 * i),
            temps_c=[20.0] * 32,
            ambient_c=22.0,
            speed_rpm=3e3,
            torque_nm=1.0,
            quality=["ok"] * 32,
        )
        for i in range(720)
    ]
    for minute in range(120):
        for f in factories:
            with repo.session_scope(f) as s:
                repo.write_records(s, data[6 * minute : 6 * minute + 6])
    pg = engine.dialect.name == "postgresql"

    def index_bytes() -> int:
        with engine.connect() as conn:
            return int(
                conn.execute(
                    sa.text("SELECT pg_indexes_size(CAST(:p AS regclass))"), {"p": partition_name(day)}
                ).scalar()
                or 0
            )

    before = index_bytes() if pg else 0
    report = retention_pass(engine, now=NOW, raw_days=30, minute_days=365)
    if not pg:
        assert report.partitions_compacted == () and report.compact_seconds < 1.0
        return
    assert report.partitions_compacted == (partition_name(day),)  # today is open: not compacted
    after = index_bytes()
    assert after < 0.7 * before, (before, after)  # measured: about 0.55 of it
    for f in factories:
        with repo.session_scope(f) as s:
            assert [r.t for r in repo.list_samples(s)] == [d.t for d in data]
    again = retention_pass(engine, now=NOW, raw_days=30, minute_days=365)
    assert again.partitions_compacted == ()  # done once
    late = SampleData(
        t=t0 - timedelta(seconds=5),
        temps_c=[21.0] * 32,
        ambient_c=22.0,
        speed_rpm=3e3,
        torque_nm=1.0,
        quality=["ok"] * 32,
    )
    with repo.session_scope(factories[0]) as s:
        repo.write_records(s, [late, data[0]])  # a late sample, and a retried one (skipped)
    with repo.session_scope(factories[0]) as s:
        assert repo.count_rows(s, SampleRow) == 721
