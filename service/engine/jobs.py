"""An identification job's inputs from the core's state: the window, its start field and the request.

Pure functions of the live state (``service.estimate.live.LiveModel``, read only), the sample history and the
configuration; the core (``service.engine.core``) calls them when the scheduler starts a job.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from model.carry import StateCovariance
from service.engine.config import CoreConfig
from service.estimate.live import LiveModel, LiveStateError, Snapshot
from service.identify.scheduler import StartJob
from service.identify.window import InsufficientWindowError, RawWindow, WindowArrays, resample_window
from service.identify.worker import JobRequest

__all__ = ["JobWindow", "Offsets", "SampleHistory", "job_request", "job_window", "raw_window"]


class SampleHistory(Protocol):
    """Read access to the sample history: the samples with t in [t_from, t_to] (epoch s) as arrays."""

    def raw_window(self, t_from: float, t_to: float) -> RawWindow: ...


@dataclass(frozen=True, eq=False)
class Offsets:
    """The sensor offsets to subtract (n,) °C and their 1σ (n,) °C (``service.acquire.calibration``)."""

    offsets_c: np.ndarray
    sd_c: np.ndarray


@dataclass(frozen=True, eq=False, kw_only=True)
class JobWindow:
    """A job's window: the live state's field at its start, the resampled arrays, the start field's error."""

    start: Snapshot
    arrays: WindowArrays
    start_cov: StateCovariance | None


def raw_window(history: SampleHistory, t_from: float, t_to: float, dt_s: float) -> RawWindow:
    """The history's samples for the grid [t_from, t_to] (s): sample times jitter around the grid, so
    the samples within half a step outside it belong to its end points (``resample_window``,
    ``LiveModel.push``) and are included."""
    half = 0.5 * dt_s
    return history.raw_window(t_from - half, t_to + half)


def job_window(job: StartJob, live: LiveModel, history: SampleHistory, config: CoreConfig) -> JobWindow:
    """The window of ``job``; raises ``InsufficientWindowError`` or ``LiveStateError`` naming why not."""
    snap = live.field_at(job.t_from)
    start_cov = live.covariance_at(snap.t) if config.carry_start_error else None
    raw = raw_window(history, snap.t, job.t_to, config.rules.dt_s)
    arrays = resample_window(raw, snap.t, job.t_to, config.rules)
    return JobWindow(start=snap, arrays=arrays, start_cov=start_cov)


def job_request(
    job: StartJob,
    window: JobWindow,
    *,
    history: SampleHistory,
    config: CoreConfig,
    offsets: Offsets | None,
) -> JobRequest:
    """What the worker needs to identify ``job`` from ``window``."""
    return JobRequest(
        job_id=job.job_id,
        window=window.arrays,
        t0_c=window.start.field_c,
        warm_start=job.warm_start,
        method=config.method,
        seed=config.seed,
        estimate_loads=config.estimate_loads,
        estimate_t0_shift=fit_start_offset(config.estimate_t0_shift, window.start),
        carry_start_error=config.carry_start_error,
        start_cov=window.start_cov,
        gap=_gap(history, window.start_cov, window.start.t, config),
        time_budget_s=config.time_budget_s,
        ci_threshold=config.ci_threshold,
        offsets_c=None if offsets is None else offsets.offsets_c,
        offset_sd_c=None if offsets is None else offsets.sd_c,
    )


def fit_start_offset(mode: str, snap: Snapshot) -> bool:
    """Whether the window's start field gets a fitted uniform offset (``estimate_t0_shift``): "initial"
    only while it still descends from the live state's initial guess (no rebase since), whose error is
    uniform (the first sample's noise)."""
    return mode == "always" or (mode == "initial" and snap.initial)


def _gap(
    history: SampleHistory, start_cov: StateCovariance | None, t_start: float, config: CoreConfig
) -> WindowArrays | None:
    """The inputs from the rebase that ``start_cov`` belongs to up to the window start (None: no gap,
    or the history no longer has it; the worker then only decays the covariance)."""
    if start_cov is None or t_start - start_cov.t_s < 0.5 * config.rules.dt_s:
        return None
    rules = replace(config.rules, min_window_s=0.0, min_good_channels=0)
    try:
        raw = raw_window(history, start_cov.t_s, t_start, config.rules.dt_s)
        return resample_window(raw, start_cov.t_s, t_start, rules)
    except (InsufficientWindowError, LiveStateError, ValueError):
        return None
