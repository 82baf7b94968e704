"""A cumulative histogram accumulator (Prometheus style) for the service's latency and duration metrics."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from service.contracts.metrics import HistogramData

__all__ = ["DURATION_BUCKETS_S", "LATENCY_BUCKETS_S", "Histogram"]


class Histogram:
    """A small thread-compatible accumulator the service can use to produce :class:`HistogramData`."""

    def __init__(self, upper_bounds: Sequence[float]) -> None:
        self._ub = tuple(float(b) for b in upper_bounds)
        self._counts = [0] * len(self._ub)
        self._count = 0
        self._sum = 0.0
        self._lock = threading.Lock()  # observed on the event loop, read by API threads

    def observe(self, value: float) -> None:
        with self._lock:
            for i, ub in enumerate(self._ub):
                if value <= ub:
                    self._counts[i] += 1
            self._count += 1
            self._sum += float(value)

    def snapshot(self) -> HistogramData:
        with self._lock:
            return HistogramData(
                upper_bounds=self._ub, counts=tuple(self._counts), count=self._count, sum=self._sum
            )


LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)
DURATION_BUCKETS_S = (0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)
