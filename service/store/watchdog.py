"""Client-side statement timeout: a hung database (a frozen link, no RST) cannot hold a thread for ever.

A frozen network path between the service and PostgreSQL is invisible to every server-side or kernel timeout:
the server never sees the statement (``statement_timeout`` never starts), and the kernel of whatever sits in
between keeps acknowledging data and keepalive probes. psycopg then waits in ``recv`` without limit. So the
service measures its own database operations:

- ``StatementWatchdog.guard(what)`` brackets one operation (a write batch, a probe, an API read);
- ``busy_s()`` is the age of the oldest operation still running: ``/healthz`` says db ``degraded`` when it
  exceeds a few seconds (``service.shell.service``), long before anything times out;
- ``busy_s(thread)`` is the same for the operations of one thread (a spindle's writer: its own health);
- a daemon thread aborts the connections of an operation that runs longer than ``abort_after_s``: for
  psycopg it shuts the socket down (the blocked ``recv`` returns, psycopg raises ``OperationalError``,
  translated to ``DatabaseUnavailableError``: the writer buffers and retries); for SQLite it calls
  ``sqlite3.Connection.interrupt()``.

What is aborted: every connection of the engine except those checked out by a thread whose operations are
all younger than ``abort_after_s`` (issue 41.2). So the late operation's own connection, the idle ones of
the pool (a frozen link holds them too; the next checkout's pre-ping replaces them) and one being connected
or pinged, but never another spindle's write in flight that is still within its time: on a frozen link that
one becomes late in its turn and is aborted then. Each engine (the writer's, the API reads') has its own
watchdog. Times here are wall (monotonic) seconds, not the service's clock: they bound real waiting.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator

from sqlalchemy import Engine, event
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.pool import ConnectionPoolEntry

from service.logctx import in_current_context

log = logging.getLogger(__name__)

__all__ = ["StatementWatchdog", "abort_connection"]


def abort_connection(dbapi_conn: DBAPIConnection) -> bool:
    """Make a blocked call on ``dbapi_conn`` (psycopg 3 or sqlite3) return with an error; True if done."""
    pgconn = getattr(dbapi_conn, "pgconn", None)
    if pgconn is not None:
        try:
            fd = os.dup(pgconn.socket)
        except Exception:  # closed already
            return False
        with socket.socket(fileno=fd) as sock, contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        return True
    interrupt = getattr(dbapi_conn, "interrupt", None)
    if callable(interrupt):
        with contextlib.suppress(Exception):
            interrupt()
            return True
    return False


class StatementWatchdog:
    """See the module docstring. ``start()`` the checking thread; ``close()`` stops it."""

    def __init__(
        self,
        engine: Engine,
        *,
        abort_after_s: float,
        poll_s: float = 0.25,
        monotonic: Callable[[], float] = time.monotonic,
        name: str = "chtc-db-watchdog",
    ) -> None:
        if not abort_after_s > 0 or not poll_s > 0:
            raise ValueError("need abort_after_s > 0 and poll_s > 0")
        self.abort_after_s = abort_after_s
        self.poll_s = poll_s
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._running: dict[int, tuple[str, float, int]] = {}  # key -> (what, start, thread ident)
        self._aborted: set[int] = set()  # operations whose connections were aborted already
        self._ids = itertools.count()
        self._conns: dict[int, DBAPIConnection] = {}
        self._owner: dict[int, int] = {}  # id(connection) -> ident of the thread that checked it out
        self.aborts = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=in_current_context(self._run), name=name, daemon=True)
        event.listen(engine, "connect", self._on_connect)
        event.listen(engine, "close", self._on_close)
        event.listen(engine, "close_detached", self._on_close)
        event.listen(engine, "checkout", self._on_checkout)
        event.listen(engine, "checkin", self._on_checkin)

    # --- connections ------------------------------------------------------------------------------
    def _on_connect(self, dbapi_conn: DBAPIConnection, _record: ConnectionPoolEntry) -> None:
        with self._lock:
            self._conns[id(dbapi_conn)] = dbapi_conn

    def _on_close(self, dbapi_conn: DBAPIConnection, *_: object) -> None:
        with self._lock:
            self._conns.pop(id(dbapi_conn), None)
            self._owner.pop(id(dbapi_conn), None)

    def _on_checkout(self, dbapi_conn: DBAPIConnection, *_: object) -> None:
        with self._lock:
            self._owner[id(dbapi_conn)] = threading.get_ident()

    def _on_checkin(self, dbapi_conn: DBAPIConnection | None, *_: object) -> None:
        with self._lock:
            self._owner.pop(id(dbapi_conn), None)

    # --- operations -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def guard(self, what: str) -> Iterator[None]:
        """Bracket one database operation (thread-safe, nestable)."""
        key = next(self._ids)
        with self._lock:
            self._running[key] = (what, self._monotonic(), threading.get_ident())
        try:
            yield
        finally:
            with self._lock:
                self._running.pop(key, None)
                self._aborted.discard(key)

    def busy(self, thread: int | None = None) -> tuple[str, float] | None:
        """(what, seconds) of the oldest operation still running (of ``thread``, a thread ident, if given),
        or None when idle."""
        with self._lock:
            ops = [v for v in self._running.values() if thread is None or v[2] == thread]
            if not ops:
                return None
            what, t0, _ = min(ops, key=lambda v: v[1])
        return what, self._monotonic() - t0

    def busy_s(self, thread: int | None = None) -> float | None:
        b = self.busy(thread)
        return None if b is None else b[1]

    def check(self) -> int:
        """Abort the connections of each operation older than ``abort_after_s``, once per operation (see the
        module docstring for which); returns how many."""
        now = self._monotonic()
        with self._lock:
            late = [
                (k, what, now - t0)
                for k, (what, t0, _) in self._running.items()
                if now - t0 > self.abort_after_s and k not in self._aborted
            ]
            if not late:
                return 0
            self._aborted.update(k for k, _, _ in late)
            old = {th for _, t0, th in self._running.values() if now - t0 > self.abort_after_s}
            young = {th for _, _, th in self._running.values()} - old
            conns = [c for key, c in self._conns.items() if self._owner.get(key) not in young]
        n = self._abort(conns)
        _, what, age = late[0]
        log.warning("database: %s not answered for %.1f s: aborted %d connection(s)", what, age, n)
        return n

    def _abort(self, conns: list[DBAPIConnection]) -> int:
        self.aborts += 1
        return sum(abort_connection(c) for c in conns)

    # --- thread -----------------------------------------------------------------------------------
    def start(self) -> StatementWatchdog:
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop checking; an operation still running is aborted (a thread stuck on a hung database would
        otherwise keep the process from exiting: a read pool's threads are joined at interpreter exit)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        deadline = self._monotonic() + 2.0
        if self.busy() is not None:
            log.warning("database: closing with an operation still waiting: aborting its connections")
        while self.busy() is not None and self._monotonic() < deadline:
            with self._lock:
                conns = list(self._conns.values())
            self._abort(conns)  # again until it ends: a statement may start just after an abort
            time.sleep(self.poll_s)

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.check()
            except Exception:  # never let the watchdog die
                log.exception("database watchdog")
