"""How late the machine woke a sleeper while a wall-time test ran.

A test whose subject keeps wall time (a replay paced by the clock, a recorder polling on it) shares a loaded
2-core box with other processes, which stall it now and then. Such a test runs a probe beside its subject:
:class:`LoopLag` as a task in the subject's event loop (it is late whenever the loop is: a stall of the
process or a blocking call on the loop), :class:`ThreadLag` in a thread (late when a thread is, as the CAN
replayer's ``MessageSync`` thread). ``max_s`` is the longest lateness seen, ``quantile(q)`` any other. The
test allows its subject the documented tolerance plus what the probe saw at the same quantile (the machine's
own lateness, which no pacing can undo), and names both when it fails.
"""

from __future__ import annotations

import asyncio
import threading
import time
from types import TracebackType

import numpy as np

__all__ = ["LoopLag", "ThreadLag"]


class _Lateness:
    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.late_s: list[float] = []

    def _add(self, slept_s: float) -> None:
        self.late_s.append(max(0.0, slept_s - self.interval_s))

    @property
    def max_s(self) -> float:
        return max(self.late_s, default=0.0)

    def quantile(self, q: float) -> float:
        return float(np.quantile(self.late_s, q)) if self.late_s else 0.0


class LoopLag(_Lateness):
    """Sleeps ``interval_s`` at a time on the running loop (``run()``, until cancelled) and keeps how late
    each sleep ended, s."""

    def __init__(self, interval_s: float = 0.005) -> None:
        super().__init__(interval_s)

    async def run(self) -> None:
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(self.interval_s)
            self._add(time.monotonic() - t0)


class ThreadLag(_Lateness):
    """A daemon thread sleeping ``interval_s`` at a time while the ``with`` block runs; keeps how late each
    sleep ended, s."""

    def __init__(self, interval_s: float = 0.005) -> None:
        super().__init__(interval_s)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lag-probe", daemon=True)

    def _run(self) -> None:
        while True:
            t0 = time.monotonic()
            if self._stop.wait(self.interval_s):
                return
            self._add(time.monotonic() - t0)

    def __enter__(self) -> ThreadLag:
        self._thread.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        self._thread.join(1.0)
