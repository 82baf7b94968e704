"""Every log record names its spindle (issue 29, ``service.logctx``): from the asyncio tasks a spindle's
context creates, from the core thread it starts, per spindle when one process hosts several, and in the line
format; a thread started without the context falls back to the process default, never to another spindle."""

from __future__ import annotations

import asyncio
import io
import logging
import threading
from collections.abc import Iterator
from datetime import UTC, datetime

import pytest
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import PlainTextResponse
from starlette.routing import Route
from starlette.testclient import TestClient

from api.spindlehdr import HEADER, SpindleHeader
from service.core.events import Event, IdsKnown, Instruction
from service.logctx import (
    LOG_FORMAT,
    NO_SPINDLE,
    SpindleFilter,
    current_spindle,
    in_current_context,
    install_logging,
    set_default,
    spindle_context,
)
from service.shell.corethread import CoreThread

log = logging.getLogger("service.test_logctx")


class _Records(logging.Handler):
    """Keeps the records it handles; its ``SpindleFilter`` stamps them in the emitting thread or task."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.addFilter(SpindleFilter())

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def spindles(self, message: str) -> list[str]:
        return [r.spindle for r in self.records if r.getMessage() == message]  # type: ignore[attr-defined]


@pytest.fixture
def records() -> Iterator[_Records]:
    handler = _Records()
    root = logging.getLogger()
    root.addHandler(handler)
    level = root.level
    root.setLevel(logging.DEBUG)
    set_default(None)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
        set_default(None)


def test_a_task_created_in_the_context_logs_its_spindle_after_the_block(records: _Records) -> None:
    async def spindle_task(started: asyncio.Event, go: asyncio.Event) -> None:
        started.set()
        await go.wait()  # the block that created it has exited by now
        log.warning("from the task")

    async def main() -> None:
        started, go = asyncio.Event(), asyncio.Event()
        with spindle_context("cell1-sp01"):
            task = asyncio.create_task(spindle_task(started, go))
        await started.wait()
        log.warning("outside")
        go.set()
        await task

    asyncio.run(main())
    assert records.spindles("from the task") == ["cell1-sp01"]
    assert records.spindles("outside") == [NO_SPINDLE]


def test_two_spindles_in_one_process_log_their_own_ids(records: _Records) -> None:
    async def spindle(sid: str) -> None:
        with spindle_context(sid):
            for _ in range(3):
                await asyncio.sleep(0)  # interleave the two
                log.warning("tick %s", sid)

    async def main() -> None:
        await asyncio.gather(spindle("a"), spindle("b"))

    asyncio.run(main())
    assert records.spindles("tick a") == ["a"] * 3 and records.spindles("tick b") == ["b"] * 3


def test_the_core_thread_logs_the_spindle_of_whoever_started_it(records: _Records) -> None:
    """The real core thread: its step fails, the thread logs the failure (``log.exception``) in its own
    thread, whose context is the starter's copy; the starter's block has ended long before."""
    threads: list[str] = []

    def step(event: Event) -> list[Instruction]:
        threads.append(threading.current_thread().name)
        raise RuntimeError("boom")

    runner = CoreThread(capacity=10)
    with spindle_context("cell2-sp05"):
        runner.start(step, lambda: None)
    set_default("the-default")  # the thread has its own context: the default does not apply to it
    runner.post(IdsKnown("ids-1", 1, 1))
    assert runner.idle(10.0)
    runner.close()
    failed = [r for r in records.records if r.getMessage() == "core: ids-1 failed"]
    assert threads == ["chtc-core"] and [r.threadName for r in failed] == ["chtc-core"]
    assert [r.spindle for r in failed] == ["cell2-sp05"]  # type: ignore[attr-defined]


def test_a_thread_started_without_the_context_gets_the_default_not_a_guess(records: _Records) -> None:
    with spindle_context("cell1-sp01"):
        plain = threading.Thread(target=lambda: log.warning("plain thread"))
        carried = threading.Thread(target=in_current_context(lambda: log.warning("carried thread")))
    for t in (plain, carried):
        t.start()
        t.join()
    assert records.spindles("plain thread") == [NO_SPINDLE]
    assert records.spindles("carried thread") == ["cell1-sp01"]
    set_default("spindle1")  # a one-spindle process: its one id
    t = threading.Thread(target=lambda: log.warning("plain again"))
    t.start()
    t.join()
    assert records.spindles("plain again") == ["spindle1"]


def test_a_carried_function_may_run_in_several_threads_at_once() -> None:
    barrier = threading.Barrier(3)
    seen: list[str] = []

    def work() -> None:
        barrier.wait(5.0)  # all three inside the (copied) context at the same time
        seen.append(current_spindle())

    with spindle_context("x"):
        carried = in_current_context(work)
    threads = [threading.Thread(target=carried) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen == ["x", "x", "x"]


def test_an_empty_id_is_refused() -> None:
    with pytest.raises(ValueError, match="spindle_id"), spindle_context(""):
        pass


def test_the_line_format_names_the_spindle() -> None:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handler.addFilter(SpindleFilter())
    record = log.makeRecord(log.name, logging.WARNING, __file__, 1, "hello", None, None)
    with spindle_context("cell4-sp12"):
        handler.handle(record)
    assert "WARNING [spindle=cell4-sp12] service.test_logctx: hello" in stream.getvalue()


def test_install_logging_adds_the_filter_to_the_root_handlers_once() -> None:
    root = logging.getLogger()
    handler = logging.StreamHandler(io.StringIO())
    root.addHandler(handler)
    try:
        install_logging(default="spindle9")
        install_logging(default="spindle9")
        assert sum(isinstance(f, SpindleFilter) for f in handler.filters) == 1
        assert current_spindle() == "spindle9"
    finally:
        root.removeHandler(handler)
        set_default(None)


def test_a_request_is_answered_as_the_apps_spindle(records: _Records) -> None:
    """The API's outermost middleware runs the request in the spindle's context: a route's log line (and the
    answer's header) name it, though the client called from outside any context."""

    async def route(request: Request) -> PlainTextResponse:
        log.warning("in the route at %s", datetime(2026, 1, 1, tzinfo=UTC).date())
        return PlainTextResponse("ok")

    app = SpindleHeader(Starlette(routes=[Route("/", route)]), spindle_id="cell5-sp02")
    with TestClient(app) as client:
        r = client.get("/")
    assert r.headers[HEADER] == "cell5-sp02"
    assert records.spindles("in the route at 2026-01-01") == ["cell5-sp02"]


def test_a_running_spindle_logs_its_id_from_its_tasks_and_threads(tmp_path, records: _Records) -> None:  # type: ignore[no-untyped-def]
    """The real runtime, its devices unreachable (nobody listens on the simulated addresses): the acquisition
    task's device warnings, the database threads' lines (the writer, SQLAlchemy's statements from the
    writer and the read pool) and the runtime's own events all name the spindle; nothing is logged outside
    its context (the process default is unset: such a line would say ``-``)."""
    from service.host.runtime import Runtime, ScaledClock
    from service.settings import Settings
    from simulator.simrig import SimAddress, make_drivers

    sql = logging.getLogger("sqlalchemy.engine")
    sql_level = sql.level
    sql.setLevel(logging.INFO)
    events = logging.getLogger("chtc.test")
    settings = Settings(
        spindle={"id": "cell9-sp01"},  # type: ignore[arg-type]
        database={"url": f"sqlite:///{tmp_path / 'ids.db'}"},  # type: ignore[arg-type]
    )

    # threads alive before this runtime starts are not its own (a database writer another test left running
    # probes and logs its SQL at any time); the main thread, where the loop runs, is
    before = {t.ident for t in threading.enumerate()} - {threading.main_thread().ident}

    async def main() -> None:
        clock = ScaledClock(20.0)
        runtime = Runtime(settings=settings, clock=clock, on_event=lambda m: events.info("%s", m))
        await asyncio.to_thread(runtime.load)
        daq, can = make_drivers(settings, SimAddress.free(speedup=20.0), clock=clock)
        records.records.clear()  # the test's own set-up (the drivers' libraries) ran outside the spindle
        try:
            await runtime.start(daq=daq, can=can, api=False)
            deadline = asyncio.get_running_loop().time() + 20.0
            while not any(r.name.startswith("drivers") for r in records.records):
                assert asyncio.get_running_loop().time() < deadline, "no device warning"
                await asyncio.sleep(0.05)
            assert runtime.service is not None
            page = runtime.service.list_identifications
            with spindle_context("cell9-sp01"):  # a read as an API request makes it (api/spindlehdr.py)
                await asyncio.to_thread(page, since=None, until=None, limit=5, offset=0)  # the read pool
        finally:
            await runtime.stop()

    try:
        asyncio.run(main())
    finally:
        sql.setLevel(sql_level)
    mine = [  # asyncio.run's own lines are outside; so are other tests' threads
        r for r in records.records if not r.name.startswith("asyncio") and r.thread not in before
    ]
    strays = [(r.threadName, r.name, r.getMessage()[:80]) for r in mine if r.spindle != "cell9-sp01"]  # type: ignore[attr-defined]
    assert strays == []
    threads = {r.threadName for r in mine}
    assert "MainThread" in threads and len(threads) >= 3, threads  # the loop's tasks and database threads
    assert any(r.name == "chtc.test" for r in mine) and any(r.name.startswith("drivers") for r in mine)
