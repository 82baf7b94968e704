"""Sensor offset calibration against a baseline at thermal equilibrium (pure state machine, no I/O).

Thermocouples and RTDs on a spindle carry constant offsets of up to ±0.3 °C (the paper's sensor
uncertainty). Unzeroed, ±0.2 °C shifts H2, H4, H5 and H7 by tens of per cent while the fit barely notices
(issue 15). When the spindle has been at rest long enough, every part sits at the ambient temperature, so
the model's value at each sensor is the ambient and ``offset_c = mean(T_c − T_ambient)`` over the rest
window (``model.identify.baseline_offsets``).

``OffsetCalibrator.handle(event) -> list[instruction]``:

- ``Reading`` (one sample): kept while the spindle is idle; when ``rest_s`` of idle samples are *at
  equilibrium* (``equilibrium``: idle throughout, the channel mean flat within ``flat_c`` over the window,
  each channel flat within ``channel_flat_c``, each channel and the channel mean within ``max_offset_c`` /
  ``mean_tol_c`` of the ambient, at least ``min_channels`` good channels) a baseline is taken:
  ``BaselineTaken(calibration)``. While the rest goes on and the newest ``rest_s`` stay at equilibrium, the
  baseline is refined silently with every further sample (all samples since the equilibrium was first seen,
  up to ``max_rest_s``): per-channel constants of only 0.03 °C already move H2/H4 by tens of per cent, so a
  long rest is worth having. The spindle must run (speed ≥ ``idle_speed_rpm``) before the next
  ``BaselineTaken``. A refinement is announced as ``BaselineRefined(calibration)`` (to be stored) each time
  it has doubled the samples of the last one announced, and once more when the rest ends, so what is
  stored is the in-memory baseline, with a few rows per rest period.
- ``BaselineRequest`` (an operator, ``POST /api/v1/sensors/baseline`` or ``chtc``): the same checks on the
  newest ``rest_s`` of samples, now: ``BaselineTaken`` or ``BaselineRejected(reason)``.

Without a baseline the offsets are unknown: ``offset_sd`` reports ``no_baseline_sd_c`` per channel (±0.3 °C
uniform: 0.17 °C) and the identification carries it in the CIs as a constant bias per channel
(``model.identify``'s ``offset_sd_c``), so offsets widen the CIs instead of biasing H silently. After a
baseline the carried 1σ is the baseline's own error: the channel's scatter / √n plus ``equilibrium_sd_c``
(a spindle never sits exactly at the ambient).

``adopt(calibration)``: a baseline from elsewhere (the commissioning's rest) when there is none; the next
rest's baseline replaces it.

Status: ``NO_BASELINE`` → ``SETTLING`` (idle, collecting) → ``CALIBRATED``; a calibrated calibrator keeps
its offsets while it settles for the next baseline. ``OffsetCalibrator(current=...)`` starts calibrated
with a stored baseline (the service restores the newest from the database, ``service.store.calibrations``).

"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime

import numpy as np
from numpy.typing import NDArray

from service.contracts.calibration import Calibration

Array = NDArray[np.float64]

__all__ = [
    "CHANNEL_FLAT_C",
    "EQUILIBRIUM_SD_C",
    "FLAT_C",
    "IDLE_SPEED_RPM",
    "MAX_OFFSET_C",
    "MAX_REST_S",
    "MEAN_TOL_C",
    "BaselineRefined",
    "BaselineRejected",
    "BaselineRequest",
    "BaselineTaken",
    "CalibrationConfig",
    "CalibrationStatus",
    "OffsetCalibrator",
    "Reading",
    "equilibrium",
]


class CalibrationStatus(enum.StrEnum):
    NO_BASELINE = "no-baseline"
    SETTLING = "settling"
    CALIBRATED = "calibrated"


# the equilibrium test's thresholds that have no settings key (temperatures °C, times s, speed rpm)
MAX_REST_S = 7200.0  # the baseline averages at most this much of one rest period
IDLE_SPEED_RPM = 100.0  # below: spindle at rest (no bearing heat)
FLAT_C = 0.05  # |drift| of the channel mean over the window (fitted line)
CHANNEL_FLAT_C = 0.4  # |drift| of one channel over the window (noise: ~0.1 °C 1σ at 30 samples)
MAX_OFFSET_C = 0.6  # |mean(T_c − T_amb)| above this: not at the ambient (or a broken sensor)
MEAN_TOL_C = 0.1  # |mean over channels of (T_c − T_amb)| above this: the spindle is warm
EQUILIBRIUM_SD_C = 0.005  # what a spindle at rest still differs from the ambient


@dataclass(frozen=True, kw_only=True)
class CalibrationConfig:
    """Thresholds of the equilibrium detector; temperatures °C, times s, speed rpm. From the settings'
    ``identification.offset_*`` and ``min_good_channels`` and this module's constants (no defaults here:
    ``service.core.config.core_config`` builds it)."""

    rest_s: float  # idle and flat this long: the equilibrium test's window (identification.offset_rest_s)
    max_rest_s: float  # MAX_REST_S
    idle_speed_rpm: float  # IDLE_SPEED_RPM
    flat_c: float  # FLAT_C
    channel_flat_c: float  # CHANNEL_FLAT_C
    max_offset_c: float  # MAX_OFFSET_C
    mean_tol_c: float  # MEAN_TOL_C
    min_channels: int  # good channels needed for a baseline (identification.min_good_channels)
    # 1σ of the offsets before a baseline (identification.offset_sd_c: uniform in ±0.3 °C, unknown)
    no_baseline_sd_c: float
    equilibrium_sd_c: float  # EQUILIBRIUM_SD_C


@dataclass(frozen=True, kw_only=True)
class Reading:
    """One sample: UTC time, temperatures (32,) °C, which are usable (32,), ambient °C, speed rpm."""

    t: datetime
    temps_c: Array
    ok: NDArray[np.bool_]
    ambient_c: float
    speed_rpm: float


@dataclass(frozen=True)
class BaselineRequest:
    """An operator asks for a baseline now (from the newest ``rest_s`` of samples)."""

    t: datetime


@dataclass(frozen=True, eq=False)
class BaselineTaken:
    calibration: Calibration


@dataclass(frozen=True, eq=False)
class BaselineRefined:
    """The same rest period's baseline over more samples (store it; no operator message)."""

    calibration: Calibration


@dataclass(frozen=True)
class BaselineRejected:
    reason: str


Event = Reading | BaselineRequest
Instruction = BaselineTaken | BaselineRefined | BaselineRejected


def equilibrium(window: list[Reading], cfg: CalibrationConfig) -> str | None:
    """Why ``window`` (oldest first) is not a thermal equilibrium, or None when it is."""
    if not window:
        return "no samples at rest"
    span = (window[-1].t - window[0].t).total_seconds()
    if span < 0.95 * cfg.rest_s:  # sample times jitter around the 10-s grid
        return f"at rest for {span:.0f} s only ({cfg.rest_s:.0f} s needed)"
    if any(abs(r.speed_rpm) >= cfg.idle_speed_rpm for r in window):
        return "the spindle ran during the window"
    excess, times = _excess(window)
    good = np.sum(np.isfinite(excess), axis=0) >= max(3, len(window) // 2)
    if good.sum() < cfg.min_channels:
        return f"{int(good.sum())} good channels ({cfg.min_channels} needed)"
    drift = _drift(times, excess[:, good], span)
    mean_excess = np.nanmean(excess[:, good], axis=1)
    level = np.nanmean(excess[:, good], axis=0)
    checks = (
        (abs(_drift(times, mean_excess[:, None], span)[0]) > cfg.flat_c, "the sensors are still drifting"),
        (np.any(np.abs(drift) > cfg.channel_flat_c), "a channel is still drifting"),
        (abs(float(np.mean(level))) > cfg.mean_tol_c, "the spindle is not at the ambient temperature"),
        (np.any(np.abs(level) > cfg.max_offset_c), "a channel is further from the ambient than an offset"),
    )
    return next((why for bad, why in checks if bad), None)


def _excess(window: list[Reading]) -> tuple[Array, Array]:
    """(T − T_amb) (n, 32) °C with NaN where unusable, and the times (n,) s from the first sample."""
    t0 = window[0].t
    excess = np.array([np.where(r.ok, r.temps_c - r.ambient_c, np.nan) for r in window], dtype=float)
    times = np.array([(r.t - t0).total_seconds() for r in window], dtype=float)
    return excess, times


def _drift(times: Array, values: Array, span: float) -> Array:
    """Change over ``span`` s of the least-squares line through each column of ``values`` (n, k), NaN-safe."""
    ok = np.isfinite(values)
    n = np.maximum(ok.sum(axis=0), 1)
    t = np.where(ok, times[:, None], 0.0)
    v = np.where(ok, values, 0.0)
    tm, vm = t.sum(axis=0) / n, v.sum(axis=0) / n
    stt = np.sum(np.where(ok, (t - tm) ** 2, 0.0), axis=0)
    stv = np.sum(np.where(ok, (t - tm) * (v - vm), 0.0), axis=0)
    return np.asarray(np.where(stt > 0, stv / np.where(stt > 0, stt, 1.0), 0.0) * span)


def take_baseline(window: list[Reading], cfg: CalibrationConfig, source: str) -> Calibration:
    """Offsets = mean(T_c − T_amb) over the window; 1σ = scatter/√n ⊕ ``equilibrium_sd_c``."""
    excess, _ = _excess(window)
    with np.errstate(invalid="ignore"):
        n = np.sum(np.isfinite(excess), axis=0)
        offsets = np.where(n > 0, np.nanmean(np.where(n > 0, excess, 0.0), axis=0), np.nan)
        centred = np.where(np.isfinite(excess), excess - np.where(n > 0, offsets, 0.0)[None, :], 0.0)
        var = np.sum(centred**2, axis=0) / np.maximum(n - 1, 1)
        scatter = np.where(n > 1, np.sqrt(var), cfg.no_baseline_sd_c)
    sd = np.sqrt(
        np.where(n > 0, scatter**2 / np.maximum(n, 1), cfg.no_baseline_sd_c**2) + cfg.equilibrium_sd_c**2
    )
    return Calibration(
        offsets_c=np.asarray(offsets),
        sd_c=np.asarray(sd),
        t_from=window[0].t,
        t_to=window[-1].t,
        samples=len(window),
        source=source,
    )


@dataclass(kw_only=True)
class OffsetCalibrator:
    """See the module docstring. ``sample_period_s`` (the acquisition's) sizes the rest window's buffer."""

    config: CalibrationConfig
    sample_period_s: float
    current: Calibration | None = None
    status: CalibrationStatus = CalibrationStatus.NO_BASELINE
    _rest: deque[Reading] = field(init=False)
    _armed: bool = field(init=False, default=True)  # False after an automatic baseline until the spindle runs

    def __post_init__(self) -> None:
        self._rest = deque(maxlen=int(self.config.max_rest_s / self.sample_period_s) + 2)
        self._eq_start: datetime | None = None
        self._announced = 0  # samples of the last baseline announced (taken or refined)
        if self.current is not None:  # a baseline restored from the database
            self.status = CalibrationStatus.CALIBRATED

    def handle(self, event: Event) -> list[Instruction]:
        """One sample or one operator request -> what happened (nothing, a baseline, a rejection)."""
        if isinstance(event, BaselineRequest):
            return self._take("manual")
        if abs(event.speed_rpm) >= self.config.idle_speed_rpm or not np.isfinite(event.ambient_c):
            return self._rest_ended()
        self._rest.append(event)
        if self.current is None:
            self.status = CalibrationStatus.SETTLING
        window = self._window()
        if equilibrium(window, self.config) is not None:
            self._eq_start = None
            return []
        if self._eq_start is None:
            self._eq_start = window[0].t
        since = [r for r in self._rest if r.t >= self._eq_start]
        refined = take_baseline(since, self.config, "auto")
        if not self._armed and self.current is not None and self.current.source == "auto":
            self.current = refined  # the same rest period: a longer average
            return self._announce_refined(2 * self._announced)
        self._armed, self._announced = False, refined.samples
        self.current, self.status = refined, CalibrationStatus.CALIBRATED
        return [BaselineTaken(refined)]

    def _rest_ended(self) -> list[Instruction]:
        out = [] if self._armed else self._announce_refined(self._announced + 1)
        self._rest.clear()
        self._armed, self._eq_start = True, None
        self.status = CalibrationStatus.CALIBRATED if self.current else CalibrationStatus.NO_BASELINE
        return out

    def _announce_refined(self, min_samples: int) -> list[Instruction]:
        """``BaselineRefined`` if the current automatic baseline has at least ``min_samples`` samples."""
        c = self.current
        if c is None or c.source != "auto" or c.samples < min_samples:
            return []
        self._announced = c.samples
        return [BaselineRefined(c)]

    def adopt(self, calibration: Calibration) -> list[Instruction]:
        """Use ``calibration`` (e.g. the commissioning's) if there is no baseline yet: ``BaselineTaken``;
        nothing when there is one (never replaced but by a rest)."""
        if self.current is not None:
            return []
        self.current, self.status = calibration, CalibrationStatus.CALIBRATED
        return [BaselineTaken(calibration)]

    def forget(self) -> None:
        """Drop the current baseline (an adopted one that does not fit the sensors): none until a rest."""
        self.current = None
        self.status = CalibrationStatus.SETTLING if self._rest else CalibrationStatus.NO_BASELINE

    def offsets(self) -> Array:
        """The offsets to subtract (32,) °C: the current baseline's, zeros without one."""
        return self.current.applied() if self.current is not None else np.zeros(32)

    def offset_sd(self, n_channels: int = 32) -> Array:
        """1σ (n_channels,) °C of the offsets still unknown, for the CIs (see the module docstring)."""
        if self.current is None:
            return np.full(n_channels, self.config.no_baseline_sd_c)
        return np.asarray(self.current.sd_c)

    def _window(self) -> list[Reading]:
        """The newest samples spanning ``rest_s``."""
        items = list(self._rest)
        if not items:
            return items
        t_end = items[-1].t
        reach = self.config.rest_s + 0.5 * self.sample_period_s
        return [r for r in items if (t_end - r.t).total_seconds() <= reach]

    def _take(self, source: str) -> list[Instruction]:
        window = self._window()
        why = equilibrium(window, self.config)
        if why is not None:
            return [BaselineRejected(f"no baseline: {why}")]
        self.current = take_baseline(window, self.config, source)
        self.status, self._announced = CalibrationStatus.CALIBRATED, self.current.samples
        return [BaselineTaken(self.current)]
