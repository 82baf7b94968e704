"""Which spindle a log line is about: ``record.spindle`` on every record, ``[spindle=<id>]`` in every line.

One process may host several spindles (issue 29), each with its own asyncio tasks and threads, so the id is
not a process-wide constant but a context variable:

- ``spindle_context(id)`` sets it for a block. Code run in the block sees it, and so does every asyncio task
  created in the block (a task copies the context at creation), and every callback a thread hands to the
  loop with ``call_soon_threadsafe`` (it copies the calling thread's context).
- A plain ``threading.Thread`` (or a pool's worker thread) starts with an empty context: a thread the service
  starts runs its target through ``in_current_context(target)``, a copy of the starter's context taken when
  the target is wrapped (``asyncio.to_thread`` copies the context itself).
- ``SpindleFilter`` stamps ``record.spindle``: the context's id, else the process default ``set_default(id)``
  (the one configured spindle of a one-spindle process), else ``"-"`` (a process hosting several spindles
  never guesses: a line outside every spindle's context says ``-``, not a wrong id).
- ``install_logging(default=id)`` sets the root handler's format (:data:`LOG_FORMAT`) and adds the filter
  to every root handler (records of any logger that propagates to the root).

Only log records are affected; a spawned process (the identification worker) has contexts of its own and
logs without an id (docs/integration.md, "Where the spindle id appears").
"""

from __future__ import annotations

import contextvars
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import ParamSpec, TypeVar

__all__ = [
    "LOG_FORMAT",
    "NO_SPINDLE",
    "SpindleFilter",
    "current_spindle",
    "in_current_context",
    "install_logging",
    "set_default",
    "spindle_context",
]

P = ParamSpec("P")
R = TypeVar("R")

NO_SPINDLE = "-"
LOG_FORMAT = "%(asctime)s %(levelname)s [spindle=%(spindle)s] %(name)s: %(message)s"

_SPINDLE: contextvars.ContextVar[str | None] = contextvars.ContextVar("chtc_spindle", default=None)
_default: list[str | None] = [None]  # the process default (one-element list: no ``global`` statement)


def set_default(spindle_id: str | None) -> None:
    """The id for code outside every ``spindle_context`` (None: ``"-"``). A one-spindle process sets its id;
    a process hosting several leaves it None."""
    _default[0] = spindle_id


def current_spindle() -> str:
    """The spindle of the code running now: the context's, else the process default, else ``"-"``."""
    return _SPINDLE.get() or _default[0] or NO_SPINDLE


@contextmanager
def spindle_context(spindle_id: str) -> Iterator[None]:
    """Run the block (and the tasks it creates) as spindle ``spindle_id``."""
    if not spindle_id:
        raise ValueError("spindle_context: spindle_id must not be empty")
    token = _SPINDLE.set(spindle_id)
    try:
        yield
    finally:
        _SPINDLE.reset(token)


def in_current_context(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` run in a copy of the caller's context as it is now (the spindle id included): the target of a
    thread, or a function handed to a thread pool. Each call runs in its own copy, so the wrapper may run in
    several threads at once."""
    ctx = contextvars.copy_context()

    def run(*args: P.args, **kwargs: P.kwargs) -> R:
        return ctx.copy().run(fn, *args, **kwargs)

    return run


class SpindleFilter(logging.Filter):
    """Stamps ``record.spindle`` (:func:`current_spindle`, evaluated in the emitting thread or task) on every
    record it sees; drops none. A record stamped already (e.g. by an adapter's ``extra``) keeps its id."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, "spindle", None):
            record.spindle = current_spindle()
        return True


def install_logging(*, default: str | None, level: int = logging.WARNING) -> None:
    """Configure the root logger once (``basicConfig`` with :data:`LOG_FORMAT`; no-op if it has handlers) and
    add a :class:`SpindleFilter` to each of its handlers that has none; ``default`` as :func:`set_default`."""
    set_default(default)
    root = logging.getLogger()
    logging.basicConfig(level=level, format=LOG_FORMAT)
    for handler in root.handlers:
        if not any(isinstance(f, SpindleFilter) for f in handler.filters):
            handler.addFilter(SpindleFilter())
