"""Database reads for the API in a small, bounded thread pool with a deadline.

An API request that reads the database (identification history, an id not in memory) must not hold one of
the server's worker threads for as long as a hung database wants. ``DbReads.run(fn, what)`` runs
``fn(session)`` in its own session on one of ``threads`` threads and waits at most ``timeout_s``:

- all threads busy (reads are piling up): ``DatabaseBusyError`` at once, nothing queued;
- no answer within ``timeout_s``: ``DatabaseTimeoutError``; the read goes on in its thread until it finishes
  or the engine's ``StatementWatchdog`` aborts it, and holds its slot until then (so a hung database costs at
  most ``threads`` threads, never the API's pool).

Both are ``service.store.errors.DatabaseUnavailableError`` (the store's tree, drawn there); the service
turns them into ``service.contracts.errors.NotReadyError`` for the API (``service.shell.archive``), which
answers 503 in its error shape, with ``Retry-After``.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import threading
from collections.abc import Callable
from typing import TypeVar

from sqlalchemy.orm import Session, sessionmaker

from service.logctx import in_current_context
from service.store.errors import DatabaseBusyError, DatabaseTimeoutError
from service.store.repository import session_scope
from service.store.watchdog import StatementWatchdog

__all__ = ["DatabaseBusyError", "DatabaseTimeoutError", "DbReads"]

T = TypeVar("T")


class DbReads:
    """See the module docstring. ``close()`` at shutdown (does not wait for stuck reads)."""

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        *,
        threads: int = 4,
        timeout_s: float = 2.0,
        watchdog: StatementWatchdog | None = None,
    ) -> None:
        if threads < 1 or not timeout_s > 0:
            raise ValueError("need threads >= 1 and timeout_s > 0")
        self._factory = session_factory
        self.timeout_s = timeout_s
        self._slots = threading.BoundedSemaphore(threads)
        self._pool = cf.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="chtc-db-read")
        self._watchdog = watchdog
        self.rejected = 0
        self.timeouts = 0

    def run(self, fn: Callable[[Session], T], what: str) -> T:
        """``fn(session)`` on a read thread, within ``timeout_s``; raises as in the module docstring."""
        if not self._slots.acquire(blocking=False):
            self.rejected += 1
            raise DatabaseBusyError(f"{what}: the database is not answering (every read is waiting)")
        try:
            fut = self._pool.submit(in_current_context(self._read), fn, what)  # the caller's spindle
        except BaseException:
            self._slots.release()
            raise
        fut.add_done_callback(lambda _f: self._slots.release())
        try:
            return fut.result(timeout=self.timeout_s)
        except cf.TimeoutError:
            self.timeouts += 1
            raise DatabaseTimeoutError(
                f"{what}: the database did not answer within {self.timeout_s:g} s"
            ) from None

    def _read(self, fn: Callable[[Session], T], what: str) -> T:
        guard = contextlib.nullcontext() if self._watchdog is None else self._watchdog.guard(what)
        with guard, session_scope(self._factory, what) as session:
            return fn(session)

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
