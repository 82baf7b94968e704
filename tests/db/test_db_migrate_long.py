"""Issue 41.4: a long migration finishes through every entry point the docs name.

A 0006 database holding 20 spindle-days of samples (172 800 at the 10-s period, one spindle: 0006 has no
spindle id yet) takes far longer to migrate than the serving statement timeout (5 s) and watchdog (6 s)
allow: ``chtc run --migrate`` (the systemd unit, the compose file, deploy/OPERATIONS.md) was aborted at 6 s
again and again. ``chtc db upgrade`` (the Helm chart's migration job) is the other entry point. Both run here
as the real command, in a subprocess, with the default database settings.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa

from service.store import migrate
from tests.db.conftest import pg_schema_url
from tests.db.tcp_proxy import free_port

pytestmark = [pytest.mark.postgres, pytest.mark.slow]  # ~10-60 s per entry point (a real migration)

DAYS = 20
PERIOD_S = 10
SAMPLES = DAYS * 86_400 // PERIOD_S  # 172 800
ROOT = Path(__file__).resolve().parents[2]


def build_0006(url: str) -> None:
    """An empty schema migrated to 0006, then 20 days of 10-s samples bulk-inserted (one statement), the
    last ending yesterday (within ``database.raw_days``: the service's retention pass keeps them)."""
    day = datetime.now(UTC).date() - timedelta(days=DAYS + 1)
    start = datetime(day.year, day.month, day.day, tzinfo=UTC)
    migrate.upgrade(url, "0006")
    eng = sa.create_engine(url)
    try:
        with eng.begin() as conn:
            conn.execute(
                sa.text(
                    "INSERT INTO samples (t, ambient_c, speed_rpm, torque_nm, temps_c, n_good, bad_channels, "
                    "can_ok, daq_ok) "
                    "SELECT CAST(:t0 AS timestamptz) + make_interval(secs => :p * i), "
                    "21.5, 12000.0 + (i % 7), 3.5, "
                    "json_build_array(30.25 + (i % 11) * 0.01, 31.5, 32.75, 33.0, 34.5, 35.25, 36.0, 37.5), "
                    "8, '{}'::json, true, true FROM generate_series(0, :n - 1) AS i"
                ),
                {"t0": start, "p": PERIOD_S, "n": SAMPLES},
            )
            assert conn.scalar(sa.text("SELECT count(*) FROM samples")) == SAMPLES
    finally:
        eng.dispose()


@pytest.fixture
def db_0006(pg_url: str, pg_schema: str) -> Iterator[str]:
    url = pg_schema_url(pg_url, pg_schema)
    build_0006(url)
    assert migrate.current_revision(url) == "0006"
    yield url


def _env(url: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        PYTHONPATH=str(ROOT),
        OPENBLAS_NUM_THREADS="1",
        OMP_NUM_THREADS="1",
        CHTC_DATABASE__URL=url,
    )
    return env


def _at_head(url: str) -> None:
    assert migrate.current_revision(url) == migrate.head_revision()
    eng = sa.create_engine(url)
    try:
        with eng.connect() as conn:
            assert conn.scalar(sa.text("SELECT count(*) FROM samples")) == SAMPLES
    finally:
        eng.dispose()


def test_chtc_db_upgrade_migrates_20_spindle_days(db_0006: str) -> None:
    cmd = [sys.executable, "-m", "service.cli", "db", "upgrade"]
    done = subprocess.run(cmd, env=_env(db_0006), capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"database at revision {migrate.head_revision()}" in done.stdout
    _at_head(db_0006)


def test_chtc_run_migrate_migrates_20_spindle_days(db_0006: str, tmp_path: Path) -> None:
    """The service starts, migrates (progress in its log), then serves; stopped once it serves."""
    log_path = tmp_path / "run.log"
    cmd = [sys.executable, "-m", "service.cli", "run", "--migrate", "--port", str(free_port())]
    with log_path.open("w") as log:
        proc = subprocess.Popen(cmd, env=_env(db_0006), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    try:
        deadline = time.monotonic() + 600
        while "chtc: serving on" not in log_path.read_text():
            assert proc.poll() is None, log_path.read_text()[-3000:]
            assert time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    text = log_path.read_text()
    print(text[-3000:])
    assert "migrate: 0006 -> 0007 applied in" in text and "migrate: done" in text, text[-3000:]
    assert "not answered for" not in text and "statement timeout" not in text, text[-3000:]
    _at_head(db_0006)
