"""``chtc demo`` re-run on its own database (issue 41 section 3): the earlier demo's accelerated clock dated
what it stored ahead of the wall clock; the new demo's plant clock starts after the newest stored time, so
no restored live state, condition or identification lies in its future."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from service.commands.demo import clock_start_after
from service.contracts.records import SampleData
from service.store import migrate
from service.store.engine import create_db_engine, make_session_factory
from service.store.repository import session_scope, write_records

NOW = datetime(2026, 3, 2, 6, 0, tzinfo=UTC)


def _db(tmp_path, *times: datetime) -> str:  # type: ignore[no-untyped-def]
    url = f"sqlite:///{tmp_path}/demo.db"
    eng = create_db_engine(url)
    migrate.upgrade(eng)
    rows = [
        SampleData(t=t, temps_c=[21.0] * 32, ambient_c=21.0, speed_rpm=0, torque_nm=0, quality=["ok"] * 32)
        for t in times
    ]
    with session_scope(make_session_factory(eng), "write") as s:
        write_records(s, rows)
    eng.dispose()
    return url


def test_the_clock_starts_after_what_an_earlier_demo_stored(tmp_path) -> None:  # type: ignore[no-untyped-def]
    ahead = NOW + timedelta(hours=3)  # 3 wall minutes of an earlier demo at x60
    url = _db(tmp_path, NOW - timedelta(hours=1), ahead)
    assert clock_start_after(url, now=NOW) == ahead + timedelta(minutes=1)


def test_the_clock_starts_now_on_an_older_or_a_fresh_database(tmp_path) -> None:  # type: ignore[no-untyped-def]
    assert clock_start_after(_db(tmp_path, NOW - timedelta(days=1)), now=NOW) is None
    assert clock_start_after(f"sqlite:///{tmp_path}/fresh.db", now=NOW) is None
