"""A replay's retention pass measures age by the log's clock (issue 41 item 16): the log's times were older
than ``raw_days`` by the wall clock, so the pass deleted the replayed samples (a restarted replay lost its
first part's raw samples). With the log's clock, the newest stored sample is "now"."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import func, select

from service.contracts.records import SampleData
from service.host.persistence import open_persistence
from service.settings import DatabaseSettings
from service.store.models import SampleRow
from service.store.repository import session_scope, write_records

WALL = datetime(2026, 11, 29, 9, 0, tzinfo=UTC)
LOG = WALL - timedelta(days=90)  # a recording three months old; raw_days 30


def _stored(tmp_path: Path, *, log_time: bool) -> tuple[int, int]:
    db = DatabaseSettings(url=f"sqlite:///{tmp_path / 'replay.db'}", raw_days=30, minute_days=365)
    p = open_persistence(db, migrate=True, clock=lambda: WALL, log_time=log_time)
    try:
        rows = [
            SampleData(t=LOG + timedelta(seconds=10 * k), temps_c=[21.0] * 32, ambient_c=21.0, speed_rpm=0,
                       torque_nm=0, quality=["ok"] * 32)
            for k in range(360)
        ]  # fmt: skip
        with session_scope(p.session_factory, "write") as s:
            write_records(s, rows)
        report = p.retention_once()
        with session_scope(p.session_factory, "count") as s:
            left = int(s.scalar(select(func.count()).select_from(SampleRow)) or 0)
        return report.raw_rows_deleted, left
    finally:
        p.close()


def test_a_replay_keeps_its_samples(tmp_path: Path) -> None:
    assert _stored(tmp_path, log_time=True) == (0, 360)


def test_a_live_service_still_ages_by_its_clock(tmp_path: Path) -> None:
    assert _stored(tmp_path, log_time=False) == (360, 0)
