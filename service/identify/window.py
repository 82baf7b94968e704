"""Turn ring-buffer samples into an identification window (pure numpy; no model, no I/O).

The acquisition delivers samples roughly every ``dt_s`` with jitter and occasional gaps. The FE model
needs a uniform grid, so the window is resampled onto ``t_from + k·dt_s`` (k = 0..n_steps) by taking, per
grid point, the nearest sample within ``dt_s/2``. A channel enters the fit (``mask``) when it is
``Quality.OK`` on at least ``min_good_fraction`` of the grid points and never misses more than
``max_gap_s`` in a row; its isolated bad or missing points are filled by linear interpolation in time
(they would otherwise bias the squared residual). Speed, torque and ambient must be finite on at least
``min_good_fraction`` of the grid too; their holes are interpolated the same way. A window whose last grid
points have no usable channel at all (the DAQ went silent, CAN alive) ends at its last good point instead:
nothing is extrapolated past the data.

Errors::

    InsufficientWindowError(ValueError)   too little good data; ``reason`` says which rule failed
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.quality import usable
from service.errors import ServiceError

__all__ = [
    "MAX_GAP_S",
    "MIN_GOOD_FRACTION",
    "InsufficientWindowError",
    "RawWindow",
    "WindowArrays",
    "WindowRules",
    "resample_window",
]


class InsufficientWindowError(ServiceError, ValueError):
    """Too little good data for an identification (the message is the user-facing reason)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


# a channel with a smaller fraction of good points in a window is masked (no settings key)
MIN_GOOD_FRACTION = 0.8
# the longest run of missing/bad points of a channel that is interpolated, s (no settings key)
MAX_GAP_S = 300.0


@dataclass(frozen=True, kw_only=True)
class WindowRules:
    """What counts as enough data; times in s. From the settings (``acquisition.sample_period_s``,
    ``identification.min_window_s``, ``identification.min_good_channels``) and this module's constants (no
    defaults here: ``service.core.config.core_config`` builds it)."""

    dt_s: float
    min_window_s: float
    min_good_channels: int
    min_good_fraction: float  # MIN_GOOD_FRACTION
    max_gap_s: float  # longest run of missing/bad points of a channel that is interpolated (MAX_GAP_S)


@dataclass(frozen=True, eq=False, kw_only=True)
class RawWindow:
    """Samples from the ring buffer: times (n,) s, temps (n,32) °C, quality (n,32) uint8, inputs (n,)."""

    times_s: np.ndarray
    temps_c: np.ndarray
    quality: np.ndarray
    ambient_c: np.ndarray
    speed_rpm: np.ndarray
    torque_nm: np.ndarray


@dataclass(frozen=True, eq=False, kw_only=True)
class WindowArrays:
    """A uniform-grid window ready for ``model.identify.Window`` (see ``service.identify.worker``)."""

    times_s: np.ndarray  # (n_steps+1,) grid instants, s
    measured_c: np.ndarray  # (n_steps+1, 32) °C, holes filled
    mask: np.ndarray  # (32,) bool: channels used in the fit
    ambient_c: np.ndarray  # (n_steps+1,) °C at the grid instants
    speed_rpm: np.ndarray  # (n_steps+1,)
    torque_nm: np.ndarray  # (n_steps+1,)
    good_fraction: np.ndarray  # (32,) fraction of grid points with an OK value per channel

    @property
    def dt_s(self) -> float:
        return float(self.times_s[1] - self.times_s[0])

    @property
    def n_steps(self) -> int:
        return len(self.times_s) - 1

    def step_inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-step (n_steps,) ambient, speed, torque: zero-order hold, step k -> k+1 uses sample k's values
        (what a sampled DAQ knows, and the convention of ``model.inputs.InputSeries`` and the plant)."""
        return self.ambient_c[:-1], self.speed_rpm[:-1], self.torque_nm[:-1]


def resample_window(raw: RawWindow, t_from: float, t_to: float, rules: WindowRules) -> WindowArrays:
    """Resample ``raw`` onto the uniform grid over [t_from, t_to]; raises InsufficientWindowError."""
    span = t_to - t_from
    if span < rules.min_window_s - 0.5 * rules.dt_s:
        raise InsufficientWindowError(
            f"window of {span:.0f} s is shorter than min_window_s {rules.min_window_s:.0f} s"
        )
    n_steps = int(np.floor(span / rules.dt_s + 0.5))  # sample times jitter around the grid
    grid = t_from + rules.dt_s * np.arange(n_steps + 1)
    idx, hit = _nearest(np.asarray(raw.times_s, dtype=float), grid, rules.dt_s / 2)
    if hit.sum() == 0:
        raise InsufficientWindowError(f"no samples between t={t_from:.0f} s and t={t_to:.0f} s")
    temps = np.where(hit[:, None], np.asarray(raw.temps_c, dtype=float)[idx], np.nan)
    q_ok = hit[:, None] & usable(np.asarray(raw.quality)[idx]) & np.isfinite(temps)
    last = _last_good_point(q_ok)
    if 0 <= last < n_steps:  # the DAQ went silent before the end: the window ends at its last good point
        if last * rules.dt_s < rules.min_window_s - 0.5 * rules.dt_s:
            raise InsufficientWindowError(
                f"the DAQ gave no usable temperature since t={grid[last]:.0f} s: "
                f"{last * rules.dt_s:.0f} s of data, need min_window_s {rules.min_window_s:.0f} s"
            )
        n_steps, grid, idx, hit = last, grid[: last + 1], idx[: last + 1], hit[: last + 1]
        temps, q_ok = temps[: last + 1], q_ok[: last + 1]
    inputs = [
        _input(np.asarray(a, dtype=float), idx=idx, hit=hit, rules=rules, name=name, grid=grid)
        for a, name in _named_inputs(raw)
    ]
    good_fraction = q_ok.mean(axis=0)
    max_run = rules.max_gap_s / rules.dt_s
    mask = (good_fraction >= rules.min_good_fraction) & np.array(
        [_longest_false_run(q_ok[:, c]) <= max_run for c in range(q_ok.shape[1])]
    )
    if mask.sum() < rules.min_good_channels:
        raise InsufficientWindowError(
            f"only {int(mask.sum())} channels had good data over the window "
            f"(need min_good_channels={rules.min_good_channels}); "
            f"bad: {_bad_channel_list(mask, good_fraction)}"
        )
    measured = temps.copy()
    for c in np.flatnonzero(mask):
        measured[:, c] = _fill(grid, temps[:, c], q_ok[:, c])
    return WindowArrays(
        times_s=grid,
        measured_c=measured,
        mask=mask,
        ambient_c=inputs[0],
        speed_rpm=inputs[1],
        torque_nm=inputs[2],
        good_fraction=good_fraction,
    )


def _named_inputs(raw: RawWindow) -> list[tuple[np.ndarray, str]]:
    return [(raw.ambient_c, "ambient_c"), (raw.speed_rpm, "speed_rpm"), (raw.torque_nm, "torque_nm")]


def _input(
    values: np.ndarray, *, idx: np.ndarray, hit: np.ndarray, rules: WindowRules, name: str, grid: np.ndarray
) -> np.ndarray:
    v = np.where(hit, values[idx], np.nan)
    ok = np.isfinite(v)
    if ok.mean() < rules.min_good_fraction:
        raise InsufficientWindowError(
            f"{name} was missing on {100 * (1 - ok.mean()):.0f} % of the window "
            f"(allowed {100 * (1 - rules.min_good_fraction):.0f} %)"
        )
    return _fill(grid, v, ok)


def _nearest(times: np.ndarray, grid: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest sample to each grid instant and whether it lies within ``tol``."""
    if len(times) == 0:
        return np.zeros(len(grid), dtype=int), np.zeros(len(grid), dtype=bool)
    pos = np.clip(np.searchsorted(times, grid), 1, max(len(times) - 1, 1))
    left = np.clip(pos - 1, 0, len(times) - 1)
    right = np.clip(pos, 0, len(times) - 1)
    pick = np.where(np.abs(times[left] - grid) <= np.abs(times[right] - grid), left, right)
    return pick, np.abs(times[pick] - grid) <= tol + 1e-9


def _fill(grid: np.ndarray, values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    if ok.all():
        return values.astype(float)
    return np.interp(grid, grid[ok], values[ok])


def _last_good_point(q_ok: np.ndarray) -> int:
    """The last grid index with any usable channel (-1: none; the per-channel rules then name the bad
    channels). Holding the last good values over a trailing DAQ outage (every channel stale) would feed the
    fit temperatures nobody measured; channels failing alone are the per-channel rules' (mask, or fill up to
    ``max_gap_s``)."""
    good = np.flatnonzero(q_ok.any(axis=1))
    return int(good[-1]) if good.size else -1


def _longest_false_run(ok: np.ndarray) -> int:
    longest = run = 0
    for v in ok:
        run = 0 if v else run + 1
        longest = max(longest, run)
    return longest


def _bad_channel_list(mask: np.ndarray, good_fraction: np.ndarray) -> str:
    bad = [f"ch{c + 1} ({100 * good_fraction[c]:.0f} % ok)" for c in np.flatnonzero(~mask)]
    return ", ".join(bad[:8]) + (" …" if len(bad) > 8 else "")
