"""The server side of the service's PostgreSQL sessions: bounded in life, ended when orphaned (issue 41.1).

A link that freezes under a transaction leaves its backend behind: the client gives up (the watchdog shuts
its socket, ``service.store.watchdog``; or its kernel's keepalives or ``tcp_user_timeout``), but its FIN is
lost with the link, so the server keeps the backend, ``idle in transaction`` or waiting for the rest of a
pipeline, holding every lock of the transaction: a batch's uncommitted rows block every retry of that batch.
PostgreSQL's own limits do not end it in time: its TCP keepalives default to the kernel's 2 h, and
``idle_in_transaction_session_timeout`` is not armed in the middle of an extended-query pipeline (psycopg's
``executemany``: measured alive 151 s past a 20-s setting). Two things bound it here:

- ``server_options()``: every session asks the server for keepalives and a ``tcp_user_timeout`` of its own
  (a dead peer is dropped within ~25 s whatever the server's configuration) and an
  ``idle_in_transaction_session_timeout``; sent as the libpq ``options`` startup parameter, so they hold from
  the first byte (merged with a URL's own ``options``, e.g. a ``search_path``);
- ``end_orphans(engine)``: each connection remembers its backend (``pg_backend_pid()`` and its
  ``backend_start``, which tells a reused pid apart); when the pool invalidates a connection (an abort, a
  lost link, a failed pre-ping), its backend becomes a suspect, and the next connection checked out, once
  the link answers again, ends the suspects still there with ``pg_terminate_backend`` (allowed on the
  sessions of one's own role). The locks go with them and the backlog is written at once.

Neither applies behind a transaction-mode pooler (PgBouncer refuses ``options``, and a server backend there
serves many clients: the pooler ends a server transaction whose client went away). A backend orphaned by a
process that is gone (restarted) is left to the server-side limits above.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import weakref

from sqlalchemy import Engine, event
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.pool import ConnectionPoolEntry

log = logging.getLogger(__name__)

__all__ = ["IDLE_IN_TRANSACTION_S", "KEEPALIVES", "end_orphans", "orphans_ended", "server_options"]

# (idle s, interval s, count): a silent peer is dropped after idle + interval x count = 25 s
KEEPALIVES = (10, 5, 3)
IDLE_IN_TRANSACTION_S = 60  # the service never leaves a transaction idle; a longer one is an orphan
_BACKEND = "chtc_backend"  # ConnectionPoolEntry.info key: (pid, backend_start) of its server session


def server_options(*, user_timeout_ms: int, base: str = "") -> str:
    """The libpq ``options`` value: ``base`` (a URL's own, e.g. ``-csearch_path=x``), then the limits."""
    idle, interval, count = KEEPALIVES
    limits = {
        "tcp_keepalives_idle": idle,
        "tcp_keepalives_interval": interval,
        "tcp_keepalives_count": count,
        "tcp_user_timeout": int(user_timeout_ms),
        "idle_in_transaction_session_timeout": 1000 * IDLE_IN_TRANSACTION_S,
    }
    return " ".join([*([base] if base else []), *(f"-c{k}={v}" for k, v in limits.items())])


class _Suspects:
    """Backends of invalidated connections, to end from the next healthy one."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: set[tuple[int, str]] = set()  # (pid, backend_start as text)
        self.ended = 0

    def add(self, backend: tuple[int, str]) -> None:
        with self._lock:
            self._pending.add(backend)

    def take(self) -> set[tuple[int, str]]:
        with self._lock:
            taken, self._pending = self._pending, set()
        return taken

    def put_back(self, backends: set[tuple[int, str]]) -> None:
        with self._lock:
            self._pending |= backends


_of: weakref.WeakKeyDictionary[Engine, _Suspects] = weakref.WeakKeyDictionary()


def orphans_ended(engine: Engine) -> int:
    """How many orphaned sessions ``engine``'s connections have ended so far."""
    suspects = _of.get(engine)
    return 0 if suspects is None else suspects.ended


def end_orphans(engine: Engine) -> None:
    """Install the bookkeeping of ``end_orphans`` (see the module docstring) on a PostgreSQL ``engine``."""
    suspects = _of.setdefault(engine, _Suspects())

    @event.listens_for(engine, "connect")
    def _remember(dbapi_conn: DBAPIConnection, record: ConnectionPoolEntry) -> None:
        cur = dbapi_conn.cursor()
        try:
            cur.execute("SELECT pid, backend_start::text FROM pg_stat_activity WHERE pid = pg_backend_pid()")
            row = cur.fetchone()
        finally:
            cur.close()
        dbapi_conn.rollback()
        if row is not None:
            record.info[_BACKEND] = (int(row[0]), str(row[1]))

    @event.listens_for(engine, "invalidate")
    def _suspect(dbapi_conn: DBAPIConnection, record: ConnectionPoolEntry, _exc: object) -> None:
        backend = record.info.pop(_BACKEND, None)
        if backend is not None:
            suspects.add(backend)

    @event.listens_for(engine, "checkout")
    def _end_suspects(dbapi_conn: DBAPIConnection, record: ConnectionPoolEntry, _proxy: object) -> None:
        todo = suspects.take()
        if not todo:
            return
        try:
            ended = _terminate(dbapi_conn, todo)
        except Exception as err:  # this connection fails too: the next one tries again
            suspects.put_back(todo)
            log.debug("database: could not end orphaned sessions yet: %s", err)
            with contextlib.suppress(Exception):
                dbapi_conn.rollback()
            return
        if ended:
            suspects.ended += len(ended)
            log.warning(
                "database: ended %d orphaned session(s) of this service left by a lost connection (pid %s)",
                len(ended),
                ", ".join(str(p) for p in ended),
            )


def _terminate(dbapi_conn: DBAPIConnection, backends: set[tuple[int, str]]) -> list[int]:
    """``pg_terminate_backend`` each of ``backends`` still there (same pid and start); the pids ended."""
    cur = dbapi_conn.cursor()
    try:
        ended = []
        for pid, start in sorted(backends):
            cur.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE pid = %s AND backend_start::text = %s AND pid <> pg_backend_pid()",
                (pid, start),
            )
            row = cur.fetchone()
            if row is not None and row[0]:
                ended.append(pid)
    finally:
        cur.close()
    dbapi_conn.rollback()
    return ended
