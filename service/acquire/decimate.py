"""Which acquired samples are stored: one per ``database.sample_store_period_s`` of sample time (pure)."""

from __future__ import annotations

import math
from datetime import datetime

__all__ = ["SampleDecimator"]


class SampleDecimator:
    """Keep one sample per ``period_s`` (``database.sample_store_period_s``) of sample time, on a grid.

    The grid is ``k * period_s`` (epoch seconds); a sample belongs to the grid instant nearest to it
    (tolerance ``period_s / 2``), and ``keep(t)`` is True for the first sample of each grid slot after the
    last kept one. Jittered stamps (a 10 s acquisition arriving at 9.7 s, 10.4 s, ...) therefore keep
    every sample, where "at least ``period_s`` after the last kept one" dropped about a third of them. A
    sample in an earlier slot than the last kept one (the clock stepped back) restarts the grid there.
    """

    def __init__(self, period_s: float) -> None:
        if not period_s > 0:
            raise ValueError(f"database.sample_store_period_s must be > 0, got {period_s!r}")
        self.period_s = period_s
        self._last_slot: int | None = None

    def slot(self, t: datetime | float) -> int:
        """The grid slot of ``t`` (a UTC ``datetime`` or epoch seconds)."""
        ts = t.timestamp() if isinstance(t, datetime) else float(t)
        return math.floor(ts / self.period_s + 0.5)

    def keep(self, t: datetime | float) -> bool:
        k = self.slot(t)
        if self._last_slot is not None and k == self._last_slot:
            return False
        self._last_slot = k
        return True
