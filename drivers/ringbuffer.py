"""Fixed-size, time-ordered in-memory store of acquisition samples (hours of data, no per-sample allocation).

Storage is preallocated numpy arrays: ``t`` float64 epoch seconds UTC, ``temps_c`` (capacity, n) float64 °C,
``ambient_c``, ``speed_rpm``, ``torque_nm`` float64, ``quality`` (capacity, n) uint8 ``Quality``, and
``can_ok``/``daq_ok`` bools. ``append`` copies into the next slot, overwriting the oldest when full.

Concurrency: one writer, any number of reader threads. The writer bumps a sequence counter to odd before
touching the arrays and back to even after (a seqlock); a reader copies what it needs and retries if the
counter moved or was odd meanwhile. After ``READ_RETRIES`` failed attempts it takes the writer's lock, so a
reader always gets a consistent copy and the writer never waits for a reader (except in that fallback).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from drivers.errors import NoDataError, SampleOrderError
from drivers.quality import Quality

READ_RETRIES = 5
R = TypeVar("R")


@dataclass(frozen=True)
class Sample:
    """One acquisition instant. ``t`` UTC; temps_c (n,) °C; ambient_c °C; speed_rpm rpm; torque_nm N·m;
    quality (n,) ``Quality`` as uint8; ``daq_ok``/``can_ok`` whether each device delivered fresh, usable
    data (False: stale, faulted or never heard from)."""

    t: datetime
    temps_c: npt.NDArray[np.float64]
    ambient_c: float
    speed_rpm: float
    torque_nm: float
    quality: npt.NDArray[np.uint8]
    daq_ok: bool = True
    can_ok: bool = True


@dataclass(frozen=True)
class SampleSpan:
    """Copies of the samples with ``t_from <= t <= t_to``, oldest first (k samples).

    t (k,) epoch seconds UTC; temps_c (k, n) °C; ambient_c, speed_rpm, torque_nm (k,); quality (k, n) uint8;
    daq_ok, can_ok (k,) bool.
    """

    t: npt.NDArray[np.float64]
    temps_c: npt.NDArray[np.float64]
    ambient_c: npt.NDArray[np.float64]
    speed_rpm: npt.NDArray[np.float64]
    torque_nm: npt.NDArray[np.float64]
    quality: npt.NDArray[np.uint8]
    daq_ok: npt.NDArray[np.bool_]
    can_ok: npt.NDArray[np.bool_]

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def times_utc(self) -> list[datetime]:
        """Sample times as aware UTC datetimes."""
        return [datetime.fromtimestamp(float(x), UTC) for x in self.t]


def _epoch_s(t: datetime | float) -> float:
    if isinstance(t, datetime):
        if t.tzinfo is None:
            raise ValueError(f"naive datetime {t.isoformat()}: timestamps must be UTC-aware")
        return t.timestamp()
    return float(t)


class RingBuffer:
    """``capacity`` samples of ``n_channels`` temperatures; see the module docstring for thread safety."""

    def __init__(self, capacity: int, n_channels: int = 32) -> None:
        if capacity < 2 or n_channels < 1:
            raise ValueError(f"need capacity >= 2 and n_channels >= 1, got {capacity}, {n_channels}")
        self.capacity, self.n_channels = capacity, n_channels
        self._t = np.zeros(capacity)
        self._temps = np.zeros((capacity, n_channels))
        self._ambient = np.zeros(capacity)
        self._speed = np.zeros(capacity)
        self._torque = np.zeros(capacity)
        self._quality = np.zeros((capacity, n_channels), dtype=np.uint8)
        self._daq_ok = np.zeros(capacity, dtype=bool)
        self._can_ok = np.zeros(capacity, dtype=bool)
        self._next = 0  # slot the next sample goes to
        self._size = 0
        self._seq = 0  # even: stable; odd: write in progress
        self._lock = threading.Lock()
        self.appended = 0  # total samples ever appended

    def __len__(self) -> int:
        return self._size

    # ------------------------------------------------------------------------------------------ writer
    def append(self, sample: Sample) -> None:
        """Store ``sample`` (its time must not be earlier than the newest stored one)."""
        self.append_values(
            sample.t,
            sample.temps_c,
            ambient_c=sample.ambient_c,
            speed_rpm=sample.speed_rpm,
            torque_nm=sample.torque_nm,
            quality=sample.quality,
            daq_ok=sample.daq_ok,
            can_ok=sample.can_ok,
        )

    def append_values(
        self,
        t: datetime | float,
        temps_c: npt.ArrayLike,
        *,
        ambient_c: float,
        speed_rpm: float,
        torque_nm: float,
        quality: npt.ArrayLike | None = None,
        daq_ok: bool = True,
        can_ok: bool = True,
    ) -> None:
        """Store one sample from plain values (t: UTC datetime or epoch s; °C, rpm, N·m).

        Raises ``SampleOrderError`` if ``t`` is earlier than the newest stored sample."""
        ts = _epoch_s(t)
        with self._lock:
            if self._size and ts < self._t[(self._next - 1) % self.capacity]:
                newest = self._t[(self._next - 1) % self.capacity]
                raise SampleOrderError(f"sample at t={ts:.3f} s is earlier than the newest at {newest:.3f} s")
            i = self._next
            self._seq += 1
            self._t[i] = ts
            self._temps[i] = temps_c
            self._ambient[i], self._speed[i], self._torque[i] = ambient_c, speed_rpm, torque_nm
            self._quality[i] = Quality.OK if quality is None else quality
            self._daq_ok[i], self._can_ok[i] = daq_ok, can_ok
            self._next = (i + 1) % self.capacity
            self._size = min(self._size + 1, self.capacity)
            self.appended += 1
            self._seq += 1

    # ------------------------------------------------------------------------------------------ readers
    def window(self, t_from: datetime | float, t_to: datetime | float) -> SampleSpan:
        """Copies of all samples with ``t_from <= t <= t_to`` (UTC datetimes or epoch s); may be empty."""
        lo, hi = _epoch_s(t_from), _epoch_s(t_to)
        return self._consistent(lambda: self._copy(self._slices(lo, hi)))

    def latest(self) -> Sample:
        """The newest sample (copies); raises ``NoDataError`` when empty."""
        return self._consistent(self._latest_unlocked)

    def time_span(self) -> tuple[float, float]:
        """(oldest, newest) sample time in epoch s; raises ``NoDataError`` when empty."""

        def span() -> tuple[float, float]:
            if not self._size:
                raise NoDataError("ring buffer is empty")
            return float(self._t[(self._next - self._size) % self.capacity]), float(self._t[self._next - 1])

        return self._consistent(span)

    def _consistent(self, read: Callable[[], R]) -> R:
        for _ in range(READ_RETRIES):
            before = self._seq
            if before % 2 == 0:
                result = read()
                if self._seq == before:
                    return result
        with self._lock:
            return read()

    def _latest_unlocked(self) -> Sample:
        if not self._size:
            raise NoDataError("ring buffer is empty")
        i = (self._next - 1) % self.capacity
        return Sample(
            t=datetime.fromtimestamp(float(self._t[i]), UTC),
            temps_c=self._temps[i].copy(),
            ambient_c=float(self._ambient[i]),
            speed_rpm=float(self._speed[i]),
            torque_nm=float(self._torque[i]),
            quality=self._quality[i].copy(),
            daq_ok=bool(self._daq_ok[i]),
            can_ok=bool(self._can_ok[i]),
        )

    def _segments(self) -> list[tuple[int, int]]:
        """Physical [a, b) index ranges holding the samples, oldest first (each sorted by time)."""
        start = (self._next - self._size) % self.capacity
        if start + self._size <= self.capacity:
            return [(start, start + self._size)]
        return [(start, self.capacity), (0, self._next)]

    def _slices(self, lo: float, hi: float) -> list[slice]:
        out = []
        for a, b in self._segments():
            seg = self._t[a:b]
            i = a + int(np.searchsorted(seg, lo, side="left"))
            j = a + int(np.searchsorted(seg, hi, side="right"))
            if j > i:
                out.append(slice(i, j))
        return out

    def _copy(self, parts: list[slice]) -> SampleSpan:
        def take(arr: npt.NDArray[Any]) -> npt.NDArray[Any]:
            if not parts:
                return arr[:0].copy()
            return np.concatenate([arr[s] for s in parts])

        return SampleSpan(
            t=take(self._t),
            temps_c=take(self._temps),
            ambient_c=take(self._ambient),
            speed_rpm=take(self._speed),
            torque_nm=take(self._torque),
            quality=take(self._quality),
            daq_ok=take(self._daq_ok),
            can_ok=take(self._can_ok),
        )
