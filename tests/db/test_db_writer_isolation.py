"""Issue 41.2: one spindle's stuck write does not degrade the others (real PostgreSQL).

Two writers (spindles s1, s2) on one engine, sharing its watchdog and its heartbeat, as a host's spindles do
(``service.host.persistence.SharedDatabase``). s1's write waits on a row lock another session holds (what a
retry meets behind an orphaned batch); s2 keeps writing. s2's status stays ok (no ``busy_s`` of s1's), the
watchdog's abort of s1's late write leaves s2's write in flight alone, and every row of both lands.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime, timedelta

import pytest
import sqlalchemy as sa

from service.contracts.health import DeviceStatus
from service.shell.health import db_health
from service.store import repository as repo
from service.store.engine import create_db_engine, make_session_factory
from service.store.models import SampleRow
from service.store.partitions import ensure_days
from service.store.watchdog import StatementWatchdog
from service.store.writer import DbWriter, Heartbeat
from tests.db.conftest import pg_schema_url, spindle_factory, wait_until
from tests.db.test_db_spindles import samples

pytestmark = pytest.mark.postgres

T1 = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
ABORT_AFTER_S = 5.0
STALL_S = 2.0  # margins for a loaded machine: s2's own writes take well under this


def hold_row(engine: sa.Engine, spindle_id: str, t: datetime) -> sa.Connection:
    """A session that inserts ``(spindle_id, t)`` and keeps its transaction open: a writer's insert of the
    same key waits on it (``ON CONFLICT DO NOTHING`` waits for the holder's outcome)."""
    with engine.begin() as c:
        ensure_days(c, [t.date()])
    conn = engine.connect()
    conn.begin()
    (row,) = samples(1, base=20.0, start=t)
    repo.insert_ignore_rows(conn, SampleRow, [{**row.values(), "spindle_id": spindle_id}])
    return conn


def status_of(writer: DbWriter) -> DeviceStatus:
    return db_health(writer, datetime.now(UTC)).status


def test_a_stuck_writer_neither_degrades_nor_aborts_its_neighbour(pg_url: str, pg_schema: str) -> None:
    from service.store import migrate

    url = pg_schema_url(pg_url, pg_schema)
    migrate.upgrade(url)
    engine = create_db_engine(url, statement_timeout_s=30.0)  # the watchdog acts first here
    other = create_db_engine(url)
    dog = StatementWatchdog(engine, abort_after_s=ABORT_AFTER_S, poll_s=0.05).start()
    beat = Heartbeat()
    common = {"watchdog": dog, "heartbeat": beat, "heartbeat_s": 0.5, "stall_s": STALL_S}
    common |= {"retry_initial_s": 0.1, "retry_max_s": 0.5}
    spindle_factory(engine, "s1"), spindle_factory(engine, "s2")
    w1 = DbWriter(make_session_factory(engine, spindle_id="s1"), name="w-s1", **common).start()  # type: ignore[arg-type]
    w2 = DbWriter(make_session_factory(engine, spindle_id="s2"), name="w-s2", **common).start()  # type: ignore[arg-type]
    held: list[sa.Connection] = []
    try:
        wait_until(lambda: w1.status().connected and w2.status().connected, what="both writers connected")
        stuck = samples(5, base=30.0, start=T1)
        held.append(hold_row(other, "s1", stuck[2].t))
        w1.submit_many(stuck)
        wait_until(lambda: (w1.status().busy_s or 0.0) > STALL_S + 0.2, what="s1's write stuck")
        assert status_of(w1) is DeviceStatus.DEGRADED

        # s2 writes on while s1 waits: its own status, its own rows
        t2 = T1 + timedelta(hours=1)
        s2_rows = samples(40, base=40.0, start=t2)
        seen2: list[tuple[DeviceStatus, float | None]] = []
        for i in range(0, 20):
            w2.submit(s2_rows[i])
            seen2.append((status_of(w2), w2.status().busy_s))
            time.sleep(0.02)
        assert w2.flush(5.0)
        # an s2 write in flight (waiting on a lock too, but young) when the watchdog aborts s1's late one
        late = held[0]
        held.append(hold_row(other, "s2", s2_rows[25].t))
        wait_until(  # s2's write starts about a second before s1's retry is aborted
            lambda: ABORT_AFTER_S - 1.5 < (w1.status().busy_s or 0.0) < ABORT_AFTER_S - 1.0,
            timeout_s=4 * ABORT_AFTER_S,
            what="s1's retry about to be aborted",
        )
        aborts = dog.aborts
        w2.submit_many(s2_rows[20:30])
        wait_until(lambda: dog.aborts > aborts, timeout_s=10.0, what="the watchdog's abort of s1's write")
        held.pop().rollback()  # s2's lock goes: its write, never aborted, goes through
        assert w2.flush(5.0)
        w2.submit_many(s2_rows[30:])
        assert w2.flush(5.0)
        for _ in range(20):
            seen2.append((status_of(w2), w2.status().busy_s))
            time.sleep(0.02)
        st2 = w2.status()
        assert st2.errors == 0 and st2.connected and st2.written == len(s2_rows), st2
        assert all(s is DeviceStatus.OK for s, _ in seen2), seen2
        assert all(b is None or b < STALL_S for _, b in seen2), seen2

        assert w1.status().errors >= 1  # s1's own write was aborted (and retried)
        late.rollback()  # s1's lock goes: its retried batch lands
        assert w1.flush(15.0)
        with other.connect() as conn:
            n = conn.execute(sa.text("SELECT spindle_id, count(*) FROM samples GROUP BY 1")).all()
        assert dict(n) == {"s1": len(stuck), "s2": len(s2_rows)}
        assert status_of(w1) is DeviceStatus.OK
    finally:
        for conn in held:
            conn.rollback()
            conn.close()
        w1.close(2.0)
        w2.close(2.0)
        dog.close()
        engine.dispose()
        other.dispose()
