"""Operating-condition change detector: a pure state machine (no I/O, no clock, no asyncio).

The service feeds it one :class:`SampleEvent` per acquisition instant (speed, torque, ambient
temperature) and acts on the instructions it returns. A *condition* is an operating point (speed rpm,
torque N·m, ambient °C). A new condition is declared when the (median-filtered) inputs leave the current
condition's reference by more than a configured threshold in at least one quantity and stay out, and
consistent with each other, for the hold time. The new condition's values are the means of the raw
samples over the hold period and it starts at the first sample of that period (the instant of the change,
not the instant of its confirmation).

- Noise: thresholds sit well above the sensor noise; the median filter removes isolated outliers.
- Short spikes (shorter than the hold time): the candidate is dropped as soon as the inputs are back within
  the thresholds of the reference.
- Slow drift: nothing happens while the drift stays within the thresholds; once it leaves them for the hold
  time the drifted point becomes the new reference (exactly one change per threshold crossing).
- A further step during the hold restarts the candidate at the newer level.
- Samples with a non-finite value (a CAN or ambient channel down) are ignored and counted; a gap longer than
  ``max_gap_s`` inside a hold period restarts the hold period.

Errors::

    DetectorError(ValueError)      a bad configuration field (named) or a sample out of time order
"""

from __future__ import annotations

import enum
import math
import statistics
from collections import deque
from dataclasses import dataclass, field

from service.errors import ServiceError

__all__ = [
    "ConditionChanged",
    "ConditionDetector",
    "DetectorConfig",
    "DetectorError",
    "DetectorStatus",
    "OperatingPoint",
    "SampleEvent",
]


class DetectorError(ServiceError, ValueError):
    """A bad detector configuration field or an event the detector cannot accept."""


class DetectorStatus(enum.Enum):
    """Where the detector is: no condition yet, settled on a condition, or holding a candidate change."""

    STARTING = "starting"
    STABLE = "stable"
    PENDING = "pending"


@dataclass(frozen=True, kw_only=True)
class OperatingPoint:
    """An operating point: spindle speed [rpm], torque [N·m], ambient temperature [°C]."""

    speed_rpm: float
    torque_nm: float
    ambient_c: float

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.speed_rpm, self.torque_nm, self.ambient_c)


@dataclass(frozen=True, kw_only=True)
class SampleEvent:
    """One acquisition instant; ``t`` in s on any monotonic axis (the service uses UTC epoch seconds)."""

    t: float
    speed_rpm: float
    torque_nm: float
    ambient_c: float


@dataclass(frozen=True, kw_only=True)
class ConditionChanged:
    """Instruction: a new operating condition started at ``t_start`` and was confirmed at ``t_confirmed``."""

    index: int
    point: OperatingPoint
    t_start: float
    t_confirmed: float
    previous: OperatingPoint | None
    reason: str


@dataclass(frozen=True, kw_only=True)
class DetectorConfig:
    """Thresholds (absolute, per quantity) and timing of the detector; times in s. The settings'
    ``[detector]`` (no defaults here: ``service.core.config.core_config`` builds it)."""

    speed_threshold_rpm: float
    torque_threshold_nm: float
    ambient_threshold_c: float
    hold_s: float
    median_samples: int
    max_gap_s: float

    def __post_init__(self) -> None:
        for name in (
            "speed_threshold_rpm",
            "torque_threshold_nm",
            "ambient_threshold_c",
            "hold_s",
            "max_gap_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise DetectorError(f"detector.{name} must be a positive finite number, got {value!r}")
        if self.median_samples < 1:
            raise DetectorError(f"detector.median_samples must be >= 1, got {self.median_samples!r}")

    @property
    def thresholds(self) -> tuple[float, float, float]:
        return (self.speed_threshold_rpm, self.torque_threshold_nm, self.ambient_threshold_c)


@dataclass(kw_only=True)
class _Candidate:
    anchor: tuple[float, float, float]
    t_start: float
    t_last: float
    samples: list[tuple[float, float, float]] = field(default_factory=list)

    def mean(self) -> OperatingPoint:
        speed, torque, ambient = (statistics.fmean(c) for c in zip(*self.samples, strict=True))
        return OperatingPoint(speed_rpm=speed, torque_nm=torque, ambient_c=ambient)


class ConditionDetector:
    """Pure condition-change detector: ``handle(event) -> list[ConditionChanged]``.

    ``reference`` restores a condition known from before a restart: the detector then starts STABLE on it, so
    the same operating point after the restart is not reported as a change.
    """

    def __init__(self, config: DetectorConfig, *, reference: OperatingPoint | None = None) -> None:
        self.config = config
        self.reference = reference
        self.status = DetectorStatus.STABLE if reference is not None else DetectorStatus.STARTING
        self.changes = 0
        self.ignored_samples = 0
        self._window: deque[tuple[float, float, float]] = deque(maxlen=self.config.median_samples)
        self._candidate: _Candidate | None = None
        self._t_last: float | None = None

    def handle(self, event: SampleEvent) -> list[ConditionChanged]:
        if not isinstance(event, SampleEvent):
            raise DetectorError(f"unknown detector event {type(event).__name__}")
        raw = (event.speed_rpm, event.torque_nm, event.ambient_c)
        if not all(math.isfinite(v) for v in raw) or not math.isfinite(event.t):
            self.ignored_samples += 1
            return []
        if self._t_last is not None and event.t < self._t_last:
            raise DetectorError(
                f"sample at t={event.t} s is older than the previous one at t={self._t_last} s"
            )
        self._t_last = event.t
        self._window.append(raw)
        filtered = self._filtered()
        return self._step(event.t, raw, filtered)

    def _filtered(self) -> tuple[float, float, float]:
        cols = zip(*self._window, strict=True)
        speed, torque, ambient = (statistics.median(c) for c in cols)
        return speed, torque, ambient

    def _deviates(self, value: tuple[float, float, float], anchor: tuple[float, float, float]) -> bool:
        return any(abs(v - a) > thr for v, a, thr in zip(value, anchor, self.config.thresholds, strict=True))

    def _step(
        self, t: float, raw: tuple[float, float, float], filtered: tuple[float, float, float]
    ) -> list[ConditionChanged]:
        ref = self.reference.as_tuple() if self.reference is not None else None
        if ref is not None and not self._deviates(filtered, ref):
            self._candidate = None
            self.status = DetectorStatus.STABLE
            return []
        cand = self._candidate
        if cand is None or self._deviates(filtered, cand.anchor) or t - cand.t_last > self.config.max_gap_s:
            cand = self._candidate = _Candidate(anchor=filtered, t_start=t, t_last=t)
        cand.samples.append(raw)
        cand.t_last = t
        self.status = DetectorStatus.PENDING if ref is not None else DetectorStatus.STARTING
        if t - cand.t_start < self.config.hold_s:
            return []
        return [self._confirm(cand, t)]

    def _confirm(self, cand: _Candidate, t: float) -> ConditionChanged:
        point = cand.mean()
        previous = self.reference
        self.reference = point
        self._candidate = None
        self.status = DetectorStatus.STABLE
        self.changes += 1
        reason = "first condition" if previous is None else self._reason(previous, point)
        return ConditionChanged(
            index=self.changes,
            point=point,
            t_start=cand.t_start,
            t_confirmed=t,
            previous=previous,
            reason=reason,
        )

    def _reason(self, old: OperatingPoint, new: OperatingPoint) -> str:
        names = ("speed", "torque", "ambient")
        units = ("rpm", "N·m", "°C")
        parts = [
            f"{n} {o:.6g} -> {v:.6g} {u}"
            for n, u, o, v, thr in zip(
                names, units, old.as_tuple(), new.as_tuple(), self.config.thresholds, strict=True
            )
            if abs(v - o) > thr
        ]
        return "; ".join(parts) or "inputs left the thresholds during the hold period"
