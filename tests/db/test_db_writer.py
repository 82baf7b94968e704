"""The buffered writer: batches in order, isolates refused records, buffers while the database is unavailable
(SQLite locked or not migrated, PostgreSQL unreachable or dropped) and loses nothing when it comes back."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from service.contracts.records import ConditionEnd, ConditionStart, DeviceEventData, Record, SampleData
from service.store import migrate
from service.store import repository as repo
from service.store.engine import create_db_engine, make_session_factory
from service.store.models import Condition, DeviceEvent, Identification, SampleRow
from service.store.writer import DbWriter
from tests.db.conftest import pg_schema_url, wait_until
from tests.db.tcp_proxy import TcpProxy, free_port
from tests.db.test_db_repository import ident

T0 = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
FAST = {"retry_initial_s": 0.02, "retry_max_s": 0.1}


def samples(n: int, start: int = 0) -> list[SampleData]:
    return [
        SampleData(
            t=T0 + timedelta(seconds=10 * i),
            temps_c=[20.0 + 0.01 * i] * 32,
            ambient_c=22.0,
            speed_rpm=4000.0,
            torque_nm=10.0,
            quality=["ok"] * 32,
        )
        for i in range(start, start + n)
    ]


def workload(n_samples: int = 120) -> list[Record]:
    return [
        ConditionStart(id=1, started_at=T0, speed_rpm=3000.0, torque_nm=8.0, ambient_c=23.2),
        *samples(n_samples),
        ident(1, 1, T0 + timedelta(minutes=20)),
        DeviceEventData(t=T0, device="can", kind="counter-gap", detail="expected 3, got 5"),
        ConditionEnd(1, T0 + timedelta(hours=1)),
        ConditionStart(
            id=2, started_at=T0 + timedelta(hours=1), speed_rpm=4000.0, torque_nm=10.0, ambient_c=22.0
        ),
        ident(2, 2, T0 + timedelta(hours=1, minutes=20)),
    ]


def counts(factory: sessionmaker[Session]) -> dict[str, int]:
    with repo.session_scope(factory) as s:
        return {
            m.__tablename__: repo.count_rows(s, m)
            for m in (Condition, Identification, DeviceEvent, SampleRow)
        }


def db_events(factory: sessionmaker[Session]) -> list[str]:
    with repo.session_scope(factory) as s:
        return [e.kind for e in reversed(repo.list_device_events(s, device="db", limit=100).items)]


@pytest.fixture
def writer_for() -> Iterator[list[DbWriter]]:
    made: list[DbWriter] = []
    yield made
    for w in made:
        w.close(timeout_s=1.0)


def test_writes_everything_in_order(factory: sessionmaker[Session], writer_for: list[DbWriter]) -> None:
    w = DbWriter(factory, batch_size=50, **FAST).start()
    writer_for.append(w)
    records = workload()
    assert w.submit_many(records) == len(records)
    assert w.flush(timeout_s=15.0)
    status = w.status()
    assert (status.connected, status.pending, status.written, status.rejected) == (True, 0, len(records), 0)
    assert status.last_ok_at is not None and status.last_ok_at.tzinfo is UTC
    assert counts(factory) == {"conditions": 2, "identifications": 2, "device_events": 1, "samples": 120}
    with repo.session_scope(factory) as s:
        assert repo.get_condition(s, 1).ended_at == T0 + timedelta(hours=1)
        assert [r.temps_c[0] for r in repo.list_samples(s)] == [r.temps_c[0] for r in samples(120)]


def test_refused_records_are_isolated_and_counted(
    factory: sessionmaker[Session], writer_for: list[DbWriter]
) -> None:
    w = DbWriter(factory, batch_size=100, **FAST)
    writer_for.append(w)
    records = workload(10)
    bad = [
        ConditionStart(id=1, started_at=T0, speed_rpm=1.0, torque_nm=1.0, ambient_c=1.0),
        ident(9, 404, T0),
    ]  # duplicate id; unknown condition
    w.submit_many([*records[:5], bad[0], *records[5:], bad[1]])
    w.start()
    assert w.flush(timeout_s=15.0)
    status = w.status()
    assert (status.written, status.rejected, status.pending) == (len(records), 2, 0)
    assert status.last_error is not None and "rejected" in status.last_error
    assert counts(factory) == {"conditions": 2, "identifications": 2, "device_events": 1, "samples": 10}


def test_buffers_until_sqlite_is_migrated(tmp_path: Path, writer_for: list[DbWriter]) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path}/late.db")
    factory = make_session_factory(eng)
    w = DbWriter(factory, batch_size=25, **FAST).start()
    writer_for.append(w)
    records = workload()
    w.submit_many(records)
    wait_until(lambda: w.status().errors >= 2 and not w.status().connected, what="write failures")
    assert w.status().pending == len(records) + 1  # + the "db unavailable" event
    assert "no such table" in (w.status().last_error or "")
    migrate.upgrade(eng)
    wait_until(lambda: w.status().pending == 0, what="the buffer to drain")
    assert w.status().connected
    assert counts(factory) == {"conditions": 2, "identifications": 2, "device_events": 3, "samples": 120}
    assert db_events(factory) == ["unavailable", "available"]
    eng.dispose()


def test_buffers_while_sqlite_is_locked(tmp_path: Path, writer_for: list[DbWriter]) -> None:
    path = tmp_path / "locked.db"
    migrate.upgrade(f"sqlite:///{path}")
    eng = create_db_engine(f"sqlite:///{path}", sqlite_busy_timeout_ms=20)
    factory = make_session_factory(eng)
    w = DbWriter(factory, batch_size=25, **FAST).start()
    writer_for.append(w)
    wait_until(lambda: w.status().connected, what="the first probe")
    locker = sqlite3.connect(path, isolation_level=None)
    locker.execute("BEGIN EXCLUSIVE")
    try:
        w.submit_many(samples(60))
        wait_until(
            lambda: w.status().errors >= 2 and not w.status().connected, what="locked-database failures"
        )
        assert "locked" in (w.status().last_error or "")
        assert w.status().pending == 61 and w.status().written == 0
    finally:
        locker.execute("ROLLBACK")
        locker.close()
    wait_until(lambda: w.status().pending == 0, what="the buffer to drain")
    assert counts(factory)["samples"] == 60 and db_events(factory) == ["unavailable", "available"]
    eng.dispose()


def test_full_buffer_drops_new_records_and_counts_them(tmp_path: Path, writer_for: list[DbWriter]) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path}/small.db")
    factory = make_session_factory(eng)
    w = DbWriter(factory, buffer_max=10, **FAST)
    writer_for.append(w)
    accepted = [w.submit(r) for r in samples(15)]
    assert accepted == [True] * 10 + [False] * 5
    w.start()  # not migrated: the first write fails, its "unavailable" event finds the buffer full too
    wait_until(lambda: w.status().errors >= 1, what="a write failure")
    assert (w.status().dropped, w.status().pending) == (6, 10)
    migrate.upgrade(eng)
    wait_until(lambda: w.status().pending == 0, what="the buffer to drain")
    with repo.session_scope(factory) as s:
        assert [r.t for r in repo.list_samples(s)] == [r.t for r in samples(10)]  # the oldest ten, in order
    eng.dispose()


def test_close_while_unavailable_reports_what_was_lost(tmp_path: Path) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path}/never.db")
    w = DbWriter(make_session_factory(eng), **FAST).start()
    w.submit_many(samples(7))
    wait_until(lambda: w.status().errors >= 1, what="a write failure")
    assert not w.flush(timeout_s=0.05)
    final = w.close(timeout_s=0.2)
    assert final.lost_on_close == 8 and final.pending == 0 and final.written == 0  # 7 samples + the event
    assert not w.submit(samples(1)[0]) and w.status().dropped == 1
    with pytest.raises(TypeError, match="not a database record"):
        w.submit("hello")  # type: ignore[arg-type]
    eng.dispose()


@pytest.mark.postgres
def test_postgres_unreachable_then_back_then_dropped_loses_nothing(
    pg_url: str, pg_schema: str, writer_for: list[DbWriter]
) -> None:
    direct = pg_schema_url(pg_url, pg_schema)
    migrate.upgrade(direct)
    target = sa.engine.make_url(pg_url)
    port = free_port()
    eng = create_db_engine(pg_schema_url(pg_url, pg_schema, port=port), connect_timeout_s=2)
    w = DbWriter(make_session_factory(eng), batch_size=40, **FAST).start()
    writer_for.append(w)
    records = workload(100)
    w.submit_many(records)
    wait_until(lambda: w.status().errors >= 2 and not w.status().connected, what="connection refusals")
    assert w.status().pending == len(records) + 1

    proxy = TcpProxy(port, (target.host or "127.0.0.1", target.port or 5432)).start()
    try:
        wait_until(lambda: w.status().pending == 0, what="the buffer to drain")
        proxy.stop()  # the server goes away under a pooled connection
        errors = w.status().errors
        w.submit_many(samples(50, start=100))
        wait_until(lambda: w.status().errors > errors and not w.status().connected, what="the dropped server")
        proxy = TcpProxy(port, proxy.target).start()
        wait_until(lambda: w.status().pending == 0, what="the buffer to drain again")
    finally:
        proxy.stop()
    check_eng = create_db_engine(direct)
    check = make_session_factory(check_eng)
    assert counts(check) == {"conditions": 2, "identifications": 2, "device_events": 5, "samples": 150}
    assert db_events(check) == ["unavailable", "available", "unavailable", "available"]
    with repo.session_scope(check) as s:
        assert [r.t for r in repo.list_samples(s)] == [r.t for r in samples(150)]
    check_eng.dispose()
    w.close(timeout_s=1.0)
    eng.dispose()


def test_concurrent_submitters_never_wait_for_a_locked_database(
    tmp_path: Path, writer_for: list[DbWriter]
) -> None:
    import threading
    import time

    path = tmp_path / "busy.db"
    migrate.upgrade(f"sqlite:///{path}")
    eng = create_db_engine(f"sqlite:///{path}", sqlite_busy_timeout_ms=1000)  # each write attempt blocks 1 s
    factory = make_session_factory(eng)
    w = DbWriter(factory, batch_size=7, **FAST).start()
    writer_for.append(w)
    locker = sqlite3.connect(path, isolation_level=None)
    locker.execute("BEGIN EXCLUSIVE")
    slowest: list[float] = []

    def submit_all(k: int) -> None:
        worst = 0.0
        for i in range(50):
            t = T0 + timedelta(seconds=i)
            started = time.perf_counter()
            w.submit(DeviceEventData(t=t, device=f"dev{k}", kind=f"e{i}"))
            worst = max(worst, time.perf_counter() - started)
        slowest.append(worst)

    threads = [threading.Thread(target=submit_all, args=(k,)) for k in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    try:
        assert max(slowest) < 0.5  # a write attempt blocks for 1 s; submit() must not
        assert w.status().written == 0
    finally:
        locker.execute("ROLLBACK")
        locker.close()
    wait_until(lambda: w.status().pending == 0, what="the buffer to drain")
    with repo.session_scope(factory) as s:
        for k in range(4):
            events = repo.list_device_events(s, device=f"dev{k}", limit=100).items
            assert [e.kind for e in reversed(events)] == [f"e{i}" for i in range(50)]
    eng.dispose()


class FrozenTime:
    """The writers' monotonic seconds, moved by the test (their clock reads T0 + that)."""

    def __init__(self) -> None:
        self.s = 0.0

    def mono(self) -> float:
        return self.s

    def clock(self) -> datetime:
        return T0 + timedelta(seconds=self.s)


def probes_of(engine: sa.Engine) -> list[str]:
    """Every ``SELECT 1`` sent on ``engine`` (the writers' probes), appended as it is sent."""
    sent: list[str] = []

    @sa.event.listens_for(engine, "before_cursor_execute")
    def _count(conn, cursor, statement, parameters, context, executemany):  # type: ignore[no-untyped-def]
        if statement.strip() == "SELECT 1":
            sent.append(statement)

    return sent


@pytest.mark.parametrize("shared", [True, False], ids=["shared", "alone"])
def test_writers_of_one_engine_share_the_idle_probe(
    engine: sa.Engine, factory: sessionmaker[Session], writer_for: list[DbWriter], shared: bool
) -> None:
    """Two idle writers on one engine (a host's spindles): with a shared ``Heartbeat`` one ``SELECT 1`` per
    ``heartbeat_s`` answers both, and a write of one stands for the other's probe; alone, each probes."""
    from service.store.writer import Heartbeat

    time_ = FrozenTime()
    sent = probes_of(engine)
    beat = Heartbeat(monotonic=time_.mono) if shared else None
    kw = {"heartbeat_s": 5.0, "heartbeat": beat, "monotonic": time_.mono, "clock": time_.clock, **FAST}
    a, b = DbWriter(factory, **kw).start(), DbWriter(factory, **kw).start()  # type: ignore[arg-type]
    writer_for.extend([a, b])
    wait_until(lambda: a.status().connected and b.status().connected, what="both writers connected")
    assert len(sent) == 2  # each one's own first probe

    def both_ok_at(s: float) -> bool:
        return a.status().last_ok_at == b.status().last_ok_at == T0 + timedelta(seconds=s)

    time_.s = 10.0  # both heartbeats due
    wait_until(lambda: both_ok_at(10.0), what="both heartbeats at 10 s")
    assert len(sent) == (3 if shared else 4)
    time_.s = 13.0  # a writes (its success at 13 s) ...
    assert a.submit(DeviceEventData(t=T0, device="can", kind="gap"))
    wait_until(lambda: a.status().written == 1, what="a's write")
    time_.s = 16.0  # ... b's heartbeat is due, a's is not
    if shared:  # b takes a's write at 13 s as its heartbeat
        wait_until(lambda: both_ok_at(13.0), what="b's heartbeat from a's write")
        assert len(sent) == 3
    else:
        wait_until(lambda: b.status().last_ok_at == T0 + timedelta(seconds=16.0), what="b's own probe")
        assert len(sent) == 5


def test_a_heartbeat_probe_that_fails_fails_the_writers_waiting_for_it() -> None:
    """The writers that ask while one probes wait for its answer: a failure is theirs too (one probe)."""
    import threading

    from service.store.errors import DatabaseUnavailableError
    from service.store.writer import Heartbeat

    time_ = FrozenTime()
    beat = Heartbeat(monotonic=time_.mono)
    release = threading.Event()
    outcomes: list[str] = []

    def failing_probe() -> tuple[float, datetime]:
        release.wait(10.0)
        raise DatabaseUnavailableError("server closed the connection")

    def ask() -> None:
        try:
            beat.beat(failing_probe, 5.0)
        except DatabaseUnavailableError as err:
            outcomes.append(str(err))

    askers = [threading.Thread(target=ask) for _ in range(3)]
    for th in askers:
        th.start()
    wait_until(lambda: beat.probes == 1, what="the first probe")
    release.set()
    for th in askers:
        th.join(10.0)
    assert beat.probes == 1 and outcomes == ["server closed the connection"] * 3
    # later, a success: a caller within max_age_s takes it, one after it probes again
    beat.ok(20.0, T0)
    time_.s = 24.0
    assert beat.beat(failing_probe, 5.0) == (20.0, T0) and beat.probes == 1
    time_.s = 26.0
    assert beat.beat(lambda: (26.0, T0), 5.0) == (26.0, T0) and beat.probes == 2


@pytest.mark.postgres
def test_a_writer_without_pre_ping_recovers_from_a_connection_the_server_ended(
    pg_url: str, pg_schema: str, writer_for: list[DbWriter]
) -> None:
    """The writers' pool has no pre-ping (``service.host.persistence``: a ``SELECT 1`` before each write
    was a fifth of the writers' time at N = 50): a pooled connection the server ended fails the next write,
    the pool is invalidated, the writer retries on a new connection and loses nothing."""
    url = pg_schema_url(pg_url, pg_schema)
    migrate.upgrade(url)
    eng = create_db_engine(url, pre_ping=False)
    w = DbWriter(make_session_factory(eng), **FAST).start()
    writer_for.append(w)
    w.submit_many(samples(5))
    assert w.flush(timeout_s=15.0)
    with eng.connect() as conn:  # the one pooled connection the writer uses
        pid = conn.exec_driver_sql("SELECT pg_backend_pid()").scalar()
    admin = sa.create_engine(pg_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        assert conn.execute(sa.text("SELECT pg_terminate_backend(:p)"), {"p": pid}).scalar()
    admin.dispose()
    w.submit_many(samples(5, start=5))
    assert w.flush(timeout_s=15.0)
    # the dead connection failed one write (a pre-ping would have replaced it unseen): retried, all written
    assert w.status().errors >= 1 and w.status().pending == 0
    check = make_session_factory(eng)
    with repo.session_scope(check) as s:
        assert [r.t for r in repo.list_samples(s)] == [r.t for r in samples(10)]
    assert db_events(check) == ["unavailable", "available"]
    w.close(timeout_s=1.0)
    eng.dispose()
