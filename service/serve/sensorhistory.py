"""The in-memory ring of recent samples behind ``ChtcService.sensor_history`` (``SensorHistoryBuffer``)."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from datetime import datetime

import numpy as np

from service.contracts.snapshots import SensorHistory

__all__ = ["SensorHistoryBuffer"]


class SensorHistoryBuffer:
    """A thread-safe ring of the last ``capacity`` samples (measured, predicted, °C) for ``sensor_history``.

    Kept in memory by the service, so it survives a dashboard reload but not a service restart.
    """

    def __init__(self, capacity: int, sensors: Sequence[tuple[int, str, str]]) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        self._lock = threading.Lock()
        self._channels = tuple(int(c) for c, _, _ in sensors)
        self._names = tuple(n for _, n, _ in sensors)
        self._roles = tuple(r for _, _, r in sensors)
        self._cap = int(capacity)
        self._t: list[datetime | None] = [None] * self._cap
        self._m = np.full((self._cap, len(self._channels)), np.nan)
        self._p = np.full((self._cap, len(self._channels)), np.nan)
        self._n = 0  # samples appended so far; slot of sample k is k % capacity

    def append(self, t: datetime, measured_c: np.ndarray, predicted_c: np.ndarray | None) -> None:
        """Add one sample; ``measured_c`` with NaN for unusable channels, ``predicted_c`` None if none yet."""
        with self._lock:
            i = self._n % self._cap
            self._t[i] = t
            self._m[i] = measured_c
            self._p[i] = np.nan if predicted_c is None else predicted_c
            self._n += 1

    def since(self, since: datetime | None) -> SensorHistory:
        """The kept samples later than ``since`` (UTC), oldest first."""
        with self._lock:
            n = min(self._n, self._cap)
            rows = [(self._n - n + k) % self._cap for k in range(n)]
            rows = [i for i in rows if since is None or _after(self._t[i], since)]
            ts = tuple(t for t in (self._t[i] for i in rows) if t is not None)
            m, p = self._m[rows], self._p[rows]  # fancy indexing copies
        return SensorHistory(
            t=ts,
            measured_c=m,
            predicted_c=p,
            channels=self._channels,
            names=self._names,
            roles=self._roles,
            capacity=self._cap,
        )


def _after(t: datetime | None, since: datetime) -> bool:
    return t is not None and t > since
