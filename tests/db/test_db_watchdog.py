"""The client-side statement watchdog and the bounded API read pool (issue 13.2), on real SQLite."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import sqlalchemy as sa

from service.contracts.errors import NotReadyError
from service.shell.archive import IdentificationArchive
from service.store.engine import create_db_engine, make_session_factory
from service.store.errors import DatabaseUnavailableError
from service.store.reads import DatabaseBusyError, DatabaseTimeoutError, DbReads
from service.store.watchdog import StatementWatchdog

ENDLESS = "WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c) SELECT max(x) FROM c"


def test_watchdog_aborts_a_statement_that_runs_too_long(tmp_path: Path) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path / 'w.db'}")
    dog = StatementWatchdog(eng, abort_after_s=0.5, poll_s=0.05).start()
    try:
        started = time.monotonic()
        with (
            pytest.raises(sa.exc.OperationalError, match="interrupted"),
            dog.guard("endless"),
            eng.connect() as conn,
        ):
            conn.execute(sa.text(ENDLESS))
        assert 0.5 <= time.monotonic() - started < 5.0
        assert dog.aborts == 1 and dog.busy() is None
    finally:
        dog.close()
        eng.dispose()


def test_busy_reports_the_oldest_running_operation() -> None:
    now = [100.0]
    dog = StatementWatchdog(sa.create_engine("sqlite://"), abort_after_s=10.0, monotonic=lambda: now[0])
    assert dog.busy() is None
    with dog.guard("probe"):
        now[0] += 4.0
        with dog.guard("write 3 records"):
            now[0] += 1.0
            assert dog.busy() == ("probe", 5.0)
    assert dog.busy_s() is None


def test_reads_time_out_and_are_bounded(tmp_path: Path) -> None:
    eng = create_db_engine(f"sqlite:///{tmp_path / 'r.db'}")
    reads = DbReads(make_session_factory(eng), threads=2, timeout_s=0.3)
    release = threading.Event()

    def hung(session: sa.orm.Session) -> int:
        release.wait(10.0)
        return int(session.execute(sa.text("SELECT 1")).scalar_one())

    try:
        assert reads.run(lambda s: int(s.execute(sa.text("SELECT 2")).scalar_one()), "quick") == 2
        for _ in range(2):  # each waits 0.3 s, then leaves its read holding a slot
            t = time.monotonic()
            with pytest.raises(DatabaseTimeoutError, match=r"within 0\.3 s"):
                reads.run(hung, "list identifications")
            assert time.monotonic() - t < 2.0
        t = time.monotonic()
        with pytest.raises(DatabaseBusyError) as err:  # both slots taken: refused at once, nothing queued
            reads.run(hung, "get identification")
        assert time.monotonic() - t < 0.1 and isinstance(err.value, DatabaseUnavailableError)
        assert not isinstance(err.value, NotReadyError)  # the store raises no API error (service.errors)
        release.set()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                assert reads.run(lambda s: 3, "after") == 3
                break
            except DatabaseBusyError:
                time.sleep(0.02)
        else:
            pytest.fail("read slots not released after the hung reads finished")
    finally:
        release.set()
        reads.close()
        eng.dispose()


def test_the_archive_answers_a_hung_database_with_not_ready(tmp_path: Path) -> None:
    """The store's busy/timeout errors become the API's NotReadyError (503) in one place, the archive."""
    eng = create_db_engine(f"sqlite:///{tmp_path / 'a.db'}")
    factory = make_session_factory(eng)
    reads = DbReads(factory, threads=1, timeout_s=0.2)
    archive = IdentificationArchive(factory, reads)
    release = threading.Event()
    try:
        with pytest.raises(DatabaseTimeoutError):  # the only slot stays taken by a hung read
            reads.run(lambda s: release.wait(10.0), "hung")
        page = {"since": None, "until": None, "limit": 10, "offset": 0}
        with pytest.raises(NotReadyError, match="list identifications") as err:
            archive.page([], **page)
        assert isinstance(err.value.__cause__, DatabaseBusyError)
        with pytest.raises(NotReadyError, match="get identification"):
            archive.get([], 7)
    finally:
        release.set()
        reads.close()
        eng.dispose()


def test_close_aborts_an_operation_still_waiting(tmp_path: Path) -> None:
    """A read stuck at shutdown would keep the process alive (pool threads are joined at exit)."""
    eng = create_db_engine(f"sqlite:///{tmp_path / 'c.db'}")
    dog = StatementWatchdog(eng, abort_after_s=60.0, poll_s=0.05).start()
    errors: list[BaseException] = []

    def endless() -> None:
        try:
            with dog.guard("endless"), eng.connect() as conn:
                conn.execute(sa.text(ENDLESS))
        except sa.exc.OperationalError as err:
            errors.append(err)

    t = threading.Thread(target=endless)
    t.start()
    deadline = time.monotonic() + 10.0
    while dog.busy() is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    dog.close()
    t.join(5.0)
    assert not t.is_alive() and len(errors) == 1 and "interrupted" in str(errors[0])
    eng.dispose()
