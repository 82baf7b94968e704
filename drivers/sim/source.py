"""A recorded or simulated timeline played back against a clock at a speed-up factor.

The simulated devices do not run the plant themselves: they read a finished timeline (any object with the
arrays of ``model.plant.PlantRun``, see :class:`Timeline`) and look up the row that belongs to the current
simulated time::

    sim_time_s = times_s[0] + speedup * (clock() - wall_start)

Values between rows are linearly interpolated (``mode="interpolate"``, the default for the plant, whose rows
are 10 s apart) or held from the last row at or before the simulated time (``mode="hold"``, used for replays
so that replayed values equal the recorded ones exactly). Status codes are always held. Past the end the
last row is held (or the timeline wraps round when ``loop=True``). ``extend(more)`` appends rows while it
plays (``chtc demo`` computes its endless machining cycle chunk by chunk).

Errors: :class:`TimelineError` (``ValueError``) names the bad array.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.errors import DriverError

__all__ = ["ArrayTimeline", "Snapshot", "Timeline", "TimelineError", "TimelineSource", "validate_timeline"]

Clock = Callable[[], float]
Mode = Literal["interpolate", "hold"]


class TimelineError(DriverError, ValueError):
    """A timeline has inconsistent or invalid arrays (the message names the array)."""


class Timeline(Protocol):
    """What the simulators need from a plant run (``model.plant.PlantRun`` satisfies it).

    ``times_s`` (n,) s, strictly increasing; ``temps_c`` (n, channels) °C; ``ambient_c`` (n,) °C;
    ``speed_rpm`` (n,) rpm; ``torque_nm`` (n,) N·m; ``status`` (n, channels) int (0 ok, 1 open, 2 range).
    """

    @property
    def times_s(self) -> NDArray[np.float64]: ...
    @property
    def temps_c(self) -> NDArray[np.float64]: ...
    @property
    def ambient_c(self) -> NDArray[np.float64]: ...
    @property
    def speed_rpm(self) -> NDArray[np.float64]: ...
    @property
    def torque_nm(self) -> NDArray[np.float64]: ...
    @property
    def status(self) -> NDArray[np.int64]: ...


@dataclass(frozen=True)
class ArrayTimeline:
    """A minimal :class:`Timeline` built from plain arrays (tests, replays, constant profiles)."""

    times_s: NDArray[np.float64]
    temps_c: NDArray[np.float64]
    ambient_c: NDArray[np.float64]
    speed_rpm: NDArray[np.float64]
    torque_nm: NDArray[np.float64]
    status: NDArray[np.int64]

    @classmethod
    def constant(
        cls,
        *,
        temps_c: float | NDArray[np.float64] = 20.0,
        ambient_c: float = 20.0,
        speed_rpm: float = 0.0,
        torque_nm: float = 0.0,
        duration_s: float = 3600.0,
        n_channels: int = 32,
    ) -> ArrayTimeline:
        """A two-row timeline holding the same values for ``duration_s`` seconds."""
        row = np.broadcast_to(np.asarray(temps_c, dtype=float), (n_channels,))
        return cls(
            times_s=np.array([0.0, duration_s]),
            temps_c=np.vstack([row, row]),
            ambient_c=np.full(2, ambient_c),
            speed_rpm=np.full(2, speed_rpm),
            torque_nm=np.full(2, torque_nm),
            status=np.zeros((2, n_channels), dtype=np.int64),
        )


def validate_timeline(run: Timeline) -> None:
    """Check shapes, finiteness of times and monotonic time; raise :class:`TimelineError` naming the array."""
    times = np.asarray(run.times_s, dtype=float)
    if times.ndim != 1 or times.size == 0:
        raise TimelineError(f"times_s: expected a non-empty 1-D array, got shape {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise TimelineError("times_s: must be finite and strictly increasing")
    n = times.size
    temps = np.asarray(run.temps_c)
    if temps.ndim != 2 or temps.shape[0] != n:
        raise TimelineError(f"temps_c: expected shape ({n}, channels), got {temps.shape}")
    if np.asarray(run.status).shape != temps.shape:
        raise TimelineError(f"status: expected shape {temps.shape}, got {np.asarray(run.status).shape}")
    for name in ("ambient_c", "speed_rpm", "torque_nm"):
        shape = np.asarray(getattr(run, name)).shape
        if shape != (n,):
            raise TimelineError(f"{name}: expected shape ({n},), got {shape}")


@dataclass(frozen=True)
class Snapshot:
    """The timeline at one simulated instant: ``t_s`` s, temperatures °C, speed rpm, torque N·m, status."""

    t_s: float
    index: int
    temps_c: NDArray[np.float64]
    ambient_c: float
    speed_rpm: float
    torque_nm: float
    status: NDArray[np.int64]


class TimelineSource:
    """Plays a :class:`Timeline` against an injected clock at ``speedup`` simulated seconds per wall second.

    ``start()`` fixes the wall-clock origin (it is called on first use otherwise); ``now()`` returns the
    :class:`Snapshot` at the current simulated time. The clock is any ``() -> float`` in seconds
    (default ``time.monotonic``), so tests can step time by hand.
    """

    def __init__(
        self,
        run: Timeline,
        *,
        speedup: float = 1.0,
        mode: Mode = "interpolate",
        loop: bool = False,
        clock: Clock = time.monotonic,
    ) -> None:
        validate_timeline(run)
        if not speedup > 0:
            raise TimelineError(f"speedup: must be > 0, got {speedup}")
        self.run: Timeline = run
        self.speedup = float(speedup)
        self.mode: Mode = mode
        self.loop = loop
        self.clock = clock
        self._wall_start: float | None = None

    @property
    def _times(self) -> NDArray[np.float64]:
        return np.asarray(self.run.times_s, dtype=float)

    def extend(self, more: Timeline) -> None:
        """Append ``more``'s rows after the last one (its ``times_s`` on its own axis, continuing
        ``run.times_s``: every time must be later than the last row). The timeline is replaced by one new
        :class:`ArrayTimeline` in a single assignment, so a reader never sees half an extension."""
        validate_timeline(more)
        if self.loop:
            raise TimelineError("extend: a looping timeline cannot grow")
        run = self.run
        if float(np.asarray(more.times_s)[0]) <= float(np.asarray(run.times_s)[-1]):
            raise TimelineError("times_s: the rows appended must come after the last row")
        joined = {
            name: np.concatenate([np.asarray(getattr(run, name)), np.asarray(getattr(more, name))])
            for name in ("times_s", "temps_c", "ambient_c", "speed_rpm", "torque_nm", "status")
        }
        self.run = ArrayTimeline(**joined)

    @property
    def n_channels(self) -> int:
        """Number of temperature channels in the timeline."""
        return int(np.asarray(self.run.temps_c).shape[1])

    @property
    def duration_s(self) -> float:
        """Simulated length of the timeline, s."""
        return float(self._times[-1] - self._times[0])

    def start(self) -> None:
        """Fix the wall-clock origin at the current clock reading (simulated time = first row)."""
        self._wall_start = self.clock()

    def wall_elapsed_s(self) -> float:
        """Wall seconds since :meth:`start` (starting now if it was not called)."""
        if self._wall_start is None:
            self.start()
        assert self._wall_start is not None
        return self.clock() - self._wall_start

    def sim_time_s(self) -> float:
        """Current simulated time, s, on the timeline's own axis (``times_s[0]`` at start)."""
        return float(self._times[0]) + self.speedup * self.wall_elapsed_s()

    def finished(self) -> bool:
        """True once the simulated time has passed the last row (never when looping)."""
        return not self.loop and self.sim_time_s() > self._times[-1]

    def now(self) -> Snapshot:
        """The snapshot at the current simulated time."""
        return self.at(self.sim_time_s())

    def at(self, t_s: float) -> Snapshot:
        """The snapshot at simulated time ``t_s`` (s), interpolated or held according to ``mode``."""
        run = self.run  # one timeline for the whole lookup (``extend`` may replace it)
        t = self._wrap(t_s)
        times = np.asarray(run.times_s, dtype=float)
        k = int(np.searchsorted(times, t, side="right")) - 1
        k = min(max(k, 0), times.size - 1)
        frac = 0.0
        if self.mode == "interpolate" and k + 1 < times.size and t > times[k]:
            frac = (t - times[k]) / (times[k + 1] - times[k])
        return Snapshot(
            t_s=t_s,
            index=k,
            temps_c=self._blend(run.temps_c, k, frac),
            ambient_c=float(self._blend(run.ambient_c, k, frac)),
            speed_rpm=float(self._blend(run.speed_rpm, k, frac)),
            torque_nm=float(self._blend(run.torque_nm, k, frac)),
            status=np.asarray(run.status[k], dtype=np.int64).copy(),
        )

    def _wrap(self, t_s: float) -> float:
        if not self.loop or self.duration_s <= 0:
            return t_s
        t0 = float(self._times[0])
        return t0 + (t_s - t0) % self.duration_s

    @staticmethod
    def _blend(values: NDArray[np.float64], k: int, frac: float) -> NDArray[np.float64]:
        arr = np.asarray(values, dtype=float)
        if frac == 0.0:
            return np.array(arr[k], dtype=float, copy=True)
        return np.asarray((1.0 - frac) * arr[k] + frac * arr[k + 1], dtype=float)
