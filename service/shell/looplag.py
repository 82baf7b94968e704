"""The event loop's lag: how late the loop runs a callback it scheduled (docs/design/threading.md).

:class:`LoopLagMonitor` sleeps ``period_s`` on the loop again and again; each wake-up's delay beyond the
period is one observation of ``chtc_event_loop_lag_seconds`` (a histogram). Its ``recent_max_s`` is the
largest lag of the last ``window_s`` seconds; past ``limit_s`` the service's health says the event loop is
degraded (``/healthz``). The lag source is injected (``observe``), so a test can drive it without a loop.
"""

from __future__ import annotations

import asyncio
import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from service.serve.histogram import Histogram

__all__ = ["LAG_BUCKETS_S", "LoopLag", "LoopLagMonitor"]

LAG_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass(frozen=True, kw_only=True)
class LoopLag:
    """The lag now: the largest of the last ``window_s`` [s] (0: none measured), the limit, the count."""

    recent_max_s: float
    limit_s: float
    window_s: float
    observations: int

    @property
    def over_limit(self) -> bool:
        return self.recent_max_s > self.limit_s


class LoopLagMonitor:
    """See the module docstring. ``run()`` on the loop (a task); ``observe`` from anywhere."""

    def __init__(
        self,
        *,
        limit_s: float = 0.25,
        period_s: float = 0.1,
        window_s: float = 30.0,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.limit_s = float(limit_s)
        self.period_s = float(period_s)
        self.window_s = float(window_s)
        self._mono = monotonic
        self.histogram = Histogram(LAG_BUCKETS_S)
        self._recent: collections.deque[tuple[float, float]] = collections.deque()  # (at, lag)
        self._lock = threading.Lock()

    def observe(self, lag_s: float) -> None:
        """One measured lag [s] (>= 0)."""
        lag = max(0.0, float(lag_s))
        now = self._mono()
        self.histogram.observe(lag)
        with self._lock:
            self._recent.append((now, lag))
            self._expire(now)

    def _expire(self, now: float) -> None:
        while self._recent and now - self._recent[0][0] > self.window_s:
            self._recent.popleft()

    def lag(self) -> LoopLag:
        with self._lock:
            self._expire(self._mono())
            worst = max((lag for _, lag in self._recent), default=0.0)
            n = self.histogram.snapshot().count
        return LoopLag(recent_max_s=worst, limit_s=self.limit_s, window_s=self.window_s, observations=n)

    async def run(self) -> None:
        """Measure until cancelled: sleep ``period_s``, observe how late the wake-up came."""
        loop = asyncio.get_running_loop()
        while True:
            due = loop.time() + self.period_s
            await asyncio.sleep(self.period_s)
            self.observe(loop.time() - due)
