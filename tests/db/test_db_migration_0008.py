"""Revision 0008 (compact samples): a populated 0007 database upgraded keeps every row (counted) and its
values (°C to 0.01, the qualities, the scalars); the read path returns the same °C floats on SQLite and
PostgreSQL; the column types' conversions and refusals."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy.dialects import postgresql
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.records import SampleData
from service.store import migrate
from service.store import repository as repo
from service.store.engine import create_db_engine
from service.store.errors import RecordRejectedError
from service.store.models import Base, SampleMinuteRow, SampleRow
from service.store.partitions import ensure_days, list_partitions
from service.store.types import centi_celsius, decode_quality_map, encode_quality_map, float32
from tests.db.conftest import spindle_factory

T0 = datetime(2026, 3, 1, 23, 50, tzinfo=UTC)  # the rows span two UTC days
N = 120  # 10-s samples: 20 min, the last 10 on the next day
SPINDLES = ("a", "b")


def _sample(i: int) -> dict[str, object]:
    temps: list[float | None] = [round(20.0 + 0.01 * i + c, 2) for c in range(32)]
    temps[3] = None
    temps[9] = 400.0 if i == 5 else temps[9]  # beyond int16 centi-degrees: becomes null
    return {
        "t": T0 + timedelta(seconds=10 * i),
        "ambient_c": 22.0 + 0.01 * (i % 7),
        "speed_rpm": 3000.0 + i,
        "torque_nm": None if i == 6 else 8.25,
        "temps_c": temps,
        "n_good": 30,
        "bad_channels": {"4": "open_circuit", "12": "stuck"} if i % 2 else {},
        "can_ok": True,
        "daq_ok": i != 7,
    }


def _minute(k: int) -> dict[str, object]:
    return {
        "t": T0 + timedelta(minutes=k),
        "n": 6,
        "ambient_c": 22.5,
        "speed_rpm": 3002.5,
        "torque_nm": 8.25,
        "speed_max_rpm": 3005.0,
        "temps_c": [20.125 + c for c in range(32)],  # a mean: not at 0.01 °C
        "n_good_min": 30,
        "can_ok": True,
        "daq_ok": False,
    }


def _fill_0007(eng: sa.Engine) -> None:
    """0007's shape, written as 0007 stored it (real[] / JSON temperatures, JSON qualities, doubles)."""
    pg = eng.dialect.name == "postgresql"
    temps_type: sa.types.TypeEngine[object] = postgresql.ARRAY(sa.REAL()) if pg else sa.JSON()
    with eng.begin() as conn:
        spindles = sa.table("spindles", sa.column("id"), sa.column("description"), sa.column("created_at"))
        conn.execute(
            spindles.insert(),
            [{"id": s, "description": "", "created_at": T0} for s in SPINDLES if s != "a"],
        )
        ensure_days(conn, [T0.date(), T0.date() + timedelta(days=1), T0.date() + timedelta(days=5)])
        cols = [*_sample(0), "spindle_id"]
        samples = sa.table(
            "samples",
            *(
                sa.column(c, temps_type if c == "temps_c" else sa.JSON() if c == "bad_channels" else None)
                for c in cols
            ),
        )
        conn.execute(samples.insert(), [_sample(i) | {"spindle_id": s} for s in SPINDLES for i in range(N)])
        mcols = [*_minute(0), "spindle_id"]
        minutes = sa.table(
            "samples_1min", *(sa.column(c, temps_type if c == "temps_c" else None) for c in mcols)
        )
        conn.execute(minutes.insert(), [_minute(k) | {"spindle_id": s} for s in SPINDLES for k in range(20)])


def _counts(eng: sa.Engine) -> dict[str, int]:
    with eng.connect() as conn:
        return {
            f"{t}/{s}": int(
                conn.execute(sa.text(f"SELECT count(*) FROM {t} WHERE spindle_id = :s"), {"s": s}).scalar()
                or 0
            )
            for t in ("samples", "samples_1min")
            for s in SPINDLES
        }


def test_0008_keeps_every_row_and_value_of_a_0007_database(db_url: str) -> None:
    eng = create_db_engine(db_url)
    try:
        migrate.upgrade(eng, "0007", spindle_id="a")
        _fill_0007(eng)
        before = _counts(eng)
        assert before == {"samples/a": N, "samples/b": N, "samples_1min/a": 20, "samples_1min/b": 20}
        migrate.upgrade(eng)
        assert migrate.current_revision(eng) == migrate.head_revision()  # 0008 and any later one
        assert _counts(eng) == before  # every row kept
        with eng.connect() as conn:
            ctx = MigrationContext.configure(
                conn, opts={"compare_type": True, "compare_server_default": True}
            )
            from tests.db.test_db_migration_0007 import _env_filter

            include = _env_filter()
            assert [d for d in compare_metadata(ctx, Base.metadata) if _kept(d, include)] == []
            if eng.dialect.name == "postgresql":
                days = [d for _, d in list_partitions(conn)]
                assert days == [T0.date(), T0.date() + timedelta(days=1), T0.date() + timedelta(days=5)]
                types = dict(
                    conn.execute(
                        sa.text(
                            "SELECT column_name, udt_name FROM information_schema.columns "
                            "WHERE table_schema = current_schema() AND table_name = 'samples'"
                        )
                    ).all()
                )
                assert (types["temps_c"], types["bad_channels"], types["speed_rpm"]) == (
                    "_int2",
                    "bytea",
                    "float4",
                )
        for s in SPINDLES:
            factory = spindle_factory(eng, s)
            with repo.session_scope(factory) as session:
                rows = repo.list_samples(session)
                minutes = repo.list_sample_minutes(session)
            assert [r.t for r in rows] == [T0 + timedelta(seconds=10 * i) for i in range(N)]
            for i, r in enumerate(rows):
                want = _sample(i)
                temps = list(want["temps_c"])  # type: ignore[call-overload]
                if i == 5 and eng.dialect.name == "postgresql":
                    temps[9] = None  # beyond int16 centi-degrees (SQLite's stored JSON is left as it was)
                assert r.temps_c == temps  # the same °C floats (0.01 °C data)
                assert (r.ambient_c, r.speed_rpm, r.torque_nm) == (
                    want["ambient_c"],
                    want["speed_rpm"],
                    want["torque_nm"],
                )
                assert (r.bad_channels, r.n_good, r.can_ok, r.daq_ok) == (
                    want["bad_channels"],
                    30,
                    True,
                    i != 7,
                )
            assert len(minutes) == 20
            assert minutes[3].temps_c[:2] == (
                [20.12, 21.12] if eng.dialect.name == "postgresql" else [20.125, 21.125]
            )  # PostgreSQL: rounded to 0.01 °C; SQLite's stored JSON is left as it was
            assert (minutes[3].speed_max_rpm, minutes[3].n, minutes[3].daq_ok) == (3005.0, 6, False)
    finally:
        eng.dispose()


def _kept(diff: object, include: object) -> bool:
    """An autogenerate difference ``env.py``'s filter would not ignore (the reflected partitions)."""
    if isinstance(diff, tuple) and diff[0] == "remove_table":
        table = diff[1]
        return bool(include(table, table.name, "table", True, None))  # type: ignore[operator]
    return True


def test_0008_downgrade_converts_back_and_keeps_every_row(db_url: str) -> None:
    eng = create_db_engine(db_url)
    try:
        migrate.upgrade(eng, "0007", spindle_id="a")
        _fill_0007(eng)
        before = _counts(eng)
        migrate.upgrade(eng)
        migrate.downgrade(eng, "0007")
        assert _counts(eng) == before
        with eng.connect() as conn:
            row = conn.execute(
                sa.text(
                    "SELECT temps_c, bad_channels, speed_rpm, ambient_c FROM samples "
                    "WHERE spindle_id = 'b' ORDER BY t"
                )
            ).all()[1]
        temps, bad, speed, ambient = row
        if isinstance(bad, str):  # SQLite JSON as text
            import json

            temps, bad = json.loads(temps), json.loads(bad)
        assert [None if v is None else float32(v) for v in temps[:5]] == [20.01, 21.01, 22.01, None, 24.01]
        assert bad == {"4": "open_circuit", "12": "stuck"} and (speed, ambient) == (3001.0, 22.01)
        migrate.upgrade(eng)
        assert _counts(eng) == before
    finally:
        eng.dispose()


def test_the_read_path_returns_the_same_celsius_floats(factory: sessionmaker[Session]) -> None:
    t = datetime(2026, 3, 2, 8, tzinfo=UTC)
    exact = [round(-40.0 + 0.01 * k * 37, 2) for k in range(32)]  # 0.01 °C data, negative and positive
    fine = [23.4567, -0.004, 327.67, 327.68, -327.68, float("nan"), None]  # a float32 map; edges of int16
    quality = ["ok"] * 7
    quality[2] = "out_of_range"
    records = [
        SampleData(
            t=t, temps_c=exact, ambient_c=21.37, speed_rpm=12345.0, torque_nm=-3.21, quality=["ok"] * 32
        ),
        SampleData(
            t=t + timedelta(seconds=10),
            temps_c=fine,
            ambient_c=21.123456,
            speed_rpm=None,
            torque_nm=1.0,
            quality=quality,
            daq_ok=False,
        ),
    ]
    with repo.session_scope(factory) as s:
        repo.write_records(s, records)
    with repo.session_scope(factory) as s:
        a, b = repo.list_samples(s)
    assert a.temps_c == exact and (a.ambient_c, a.speed_rpm, a.torque_nm) == (21.37, 12345.0, -3.21)
    assert (a.n_good, a.bad_channels) == (32, {})
    assert b.temps_c == [23.46, -0.0, 327.67, None, -327.68, None, None]  # to 0.01 °C; beyond int16: null
    assert (b.ambient_c, b.speed_rpm, b.torque_nm) == (21.123455, None, 1.0)  # float32's nearest
    assert (b.n_good, b.bad_channels, b.daq_ok) == (6, {"3": "out_of_range"}, False)


def test_an_unknown_quality_label_is_refused_naming_it(factory: sessionmaker[Session]) -> None:
    t = datetime(2026, 3, 2, 8, tzinfo=UTC)
    bad = SampleData(
        t=t, temps_c=[20.0, 21.0], ambient_c=20.0, speed_rpm=0.0, torque_nm=0.0, quality=["ok", "smoke"]
    )
    with pytest.raises(RecordRejectedError, match="smoke"), repo.session_scope(factory) as s:
        repo.write_records(s, [bad])
    with repo.session_scope(factory) as s:
        assert repo.count_rows(s, SampleRow) == 0 and repo.count_rows(s, SampleMinuteRow) == 0


def test_centi_celsius_and_the_quality_bytes() -> None:
    assert [centi_celsius(v) for v in (23.45, -0.005, 327.67, 327.675, -327.68, -327.69, None)] == [
        2345,
        0,
        32767,
        None,
        -32768,
        None,
        None,
    ]
    assert centi_celsius(float("inf")) is None and float32(23.45) == 23.45 and float32(0.1 + 0.2) == 0.3
    bad = {"12": "stuck", "4": "open_circuit", "255": "fault"}
    assert encode_quality_map(bad) == bytes((4, 2, 12, 5, 255, 7))
    assert decode_quality_map(encode_quality_map(bad)) == bad and encode_quality_map({}) == b""
    with pytest.raises(ValueError, match="256"):
        encode_quality_map({"256": "stale"})
    with pytest.raises(ValueError, match="pairs"):
        decode_quality_map(b"\x01")
