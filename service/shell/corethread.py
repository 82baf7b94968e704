"""Where the core's per-event work runs: inline (the caller's thread) or in one dedicated thread fed by a
bounded queue (docs/design/threading.md).

The shell (``service.shell.service``) hands every event to a :class:`CoreRunner`. Two implementations:

- :class:`InlineRunner`: the event is handled at once in the caller's thread (offline runs, the compensation
  bench on its manual clock, the tests that drive the shell synchronously);
- :class:`CoreThread`: the events queue up, in order, for one thread (``chtc-core``) that runs the core's
  ``handle`` (the Kalman update, the growth terms' bookkeeping, the map's) and publishes the new view. The
  event loop only enqueues (``post``) and never waits; an API thread's request waits for its answer
  (``call``). The backlog is bounded: a sample past ``capacity`` is dropped and counted (``dropped``); the
  oldest waiting sample's time stamp is ``pending_since`` (the shell publishes it: past
  ``max_core_lag_s`` the served values say ``core_behind``); how long each event waited is ``wait_s`` (a
  histogram).

Errors::

    CoreClosedError(ServiceError, RuntimeError)   an event posted after ``close()``
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Protocol

from service.core.events import Event, Instruction, SampleReceived
from service.errors import ServiceError
from service.logctx import in_current_context
from service.serve.histogram import Histogram

__all__ = ["WAIT_BUCKETS_S", "CoreClosedError", "CoreLoad", "CoreRunner", "CoreThread", "InlineRunner"]

log = logging.getLogger(__name__)
Step = Callable[[Event], list[Instruction]]
WAIT_BUCKETS_S = (0.001, 0.005, 0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class CoreClosedError(ServiceError, RuntimeError):
    """The core thread was closed: no event is taken any more."""


@dataclass(frozen=True, kw_only=True)
class CoreLoad:
    """The backlog now: ``queued`` events, ``dropped`` samples so far (queue full), ``handled`` events,
    ``capacity``; ``threaded`` False for the inline runner (no queue at all)."""

    threaded: bool
    queued: int
    capacity: int
    handled: int
    dropped: int


class CoreRunner(Protocol):
    """How the shell runs ``step`` (its per-event work) for each event."""

    def start(self, step: Step, on_change: Callable[[], None]) -> None:
        """Begin; ``on_change`` is called (from any thread) whenever ``pending_since`` may have changed."""

    def post(self, event: Event) -> None:
        """Handle ``event`` in order, without waiting for it (the event loop)."""

    def call(self, event: Event, timeout_s: float) -> list[Instruction]:
        """Handle ``event`` in order and return its instructions (an API thread's request)."""

    @property
    def pending_since(self) -> datetime | None: ...

    def load(self) -> CoreLoad: ...

    def wait_s(self) -> Histogram | None: ...

    def idle(self, timeout_s: float) -> bool:
        """Wait until every event posted so far is handled; False on timeout."""

    def close(self) -> None: ...


class InlineRunner:
    """Every event handled at once in the caller's thread (one caller at a time)."""

    def __init__(self) -> None:
        self._step: Step | None = None
        self._handled = 0

    def start(self, step: Step, on_change: Callable[[], None]) -> None:
        self._step = step

    def post(self, event: Event) -> None:
        self.call(event, 0.0)

    def call(self, event: Event, timeout_s: float) -> list[Instruction]:
        assert self._step is not None, "start() first"
        self._handled += 1
        return self._step(event)

    @property
    def pending_since(self) -> datetime | None:
        return None

    def load(self) -> CoreLoad:
        return CoreLoad(threaded=False, queued=0, capacity=0, handled=self._handled, dropped=0)

    def wait_s(self) -> Histogram | None:
        return None

    def idle(self, timeout_s: float) -> bool:
        return True

    def close(self) -> None:
        return None


@dataclass(frozen=True)
class _Item:
    event: Event
    queued_at: float  # time.monotonic()
    reply: cf.Future[list[Instruction]] | None


class CoreThread:
    """See the module docstring. ``capacity``: samples kept waiting at most (requests and outcomes are never
    dropped); ``monotonic`` is injected for tests."""

    def __init__(self, *, capacity: int = 1000, monotonic: Callable[[], float] = time.monotonic) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        self.capacity = capacity
        self._mono = monotonic
        self._queue: collections.deque[_Item] = collections.deque()
        self._cond = threading.Condition()
        self._step: Step | None = None
        self._on_change: Callable[[], None] = lambda: None
        self._thread: threading.Thread | None = None
        self._closed = False
        self._busy = False
        self._handled = 0
        self._dropped = 0
        self._samples: collections.deque[datetime] = collections.deque()  # waiting samples' time stamps
        self._wait = Histogram(WAIT_BUCKETS_S)

    def start(self, step: Step, on_change: Callable[[], None]) -> None:
        self._step, self._on_change = step, on_change
        # the starter's context (its spindle id, service.logctx) goes with the thread
        self._thread = threading.Thread(target=in_current_context(self._run), name="chtc-core", daemon=True)
        self._thread.start()

    # --- producers
    def post(self, event: Event) -> None:
        self._put(event, None)

    def call(self, event: Event, timeout_s: float) -> list[Instruction]:
        reply: cf.Future[list[Instruction]] = cf.Future()
        self._put(event, reply)
        return reply.result(timeout=timeout_s)

    def _put(self, event: Event, reply: cf.Future[list[Instruction]] | None) -> None:
        sample = event.sample.t if isinstance(event, SampleReceived) else None
        with self._cond:
            if self._closed:
                raise CoreClosedError("the core thread is closed")
            if sample is not None and len(self._samples) >= self.capacity:
                self._dropped += 1
                if self._dropped == 1 or self._dropped % 100 == 0:
                    log.warning("core backlog full (%d samples): %d dropped", self.capacity, self._dropped)
                return
            first = sample is not None and not self._samples
            if sample is not None:
                self._samples.append(sample)
            self._queue.append(_Item(event, self._mono(), reply))
            self._cond.notify_all()
        if first:
            self._on_change()

    # --- the thread
    def _run(self) -> None:
        assert self._step is not None
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if not self._queue:
                    return
                item = self._queue.popleft()
                self._busy = True
            self._wait.observe(self._mono() - item.queued_at)
            self._handle(item)
            with self._cond:
                if isinstance(item.event, SampleReceived):
                    self._samples.popleft()
                self._busy = False
                self._handled += 1
                self._cond.notify_all()
            self._on_change()

    def _handle(self, item: _Item) -> None:
        assert self._step is not None
        try:
            out = self._step(item.event)
        except Exception as err:  # a request's caller raises it; a posted event's failure is logged
            if item.reply is not None:
                item.reply.set_exception(err)
            else:
                log.exception("core: %s failed", item.event.event_id)
            return
        if item.reply is not None:
            item.reply.set_result(out)

    # --- readers
    @property
    def pending_since(self) -> datetime | None:
        """The time stamp of the oldest sample posted and not handled yet (None: none waits)."""
        with self._cond:
            return self._samples[0] if self._samples else None

    def load(self) -> CoreLoad:
        with self._cond:
            return CoreLoad(
                threaded=True,
                queued=len(self._queue),
                capacity=self.capacity,
                handled=self._handled,
                dropped=self._dropped,
            )

    def wait_s(self) -> Histogram:
        return self._wait

    def idle(self, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout=timeout_s)

    def close(self, timeout_s: float = 10.0) -> None:
        """Handle what is queued (up to ``timeout_s``), then stop the thread."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
