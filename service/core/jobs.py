"""An identification job's inputs from the core's state: the window, its start field and the request.

Pure functions of the live state (``service.estimate.state.FilteredState``, read only), the sample history and
the configuration; the core (``service.core.machine``) calls them when the scheduler starts a job. A window
starts from the filtered state at its start (mean and covariance: ``start_cov``), never before the state has
converged since the (re)start (``FilteredState.ready_at``).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Protocol

import numpy as np

from service.core.config import CoreConfig
from service.estimate.live import LiveStateError
from service.estimate.state import FilteredState, StateSnapshot
from service.identify.scheduler import StartJob
from service.identify.window import RawWindow, WindowArrays, resample_window
from service.identify.worker import JobRequest

__all__ = [
    "STATE_CONVERGING",
    "JobWindow",
    "Offsets",
    "SampleHistory",
    "StateConverging",
    "job_request",
    "job_window",
    "raw_window",
]

STATE_CONVERGING = "state_converging"


class StateConverging(LiveStateError):
    """No window yet: the live state has not converged since the (re)start (message starts with the code
    ``state_converging``)."""


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
    """A job's window: the filtered state at its start (mean, covariance, field) and the resampled arrays."""

    start: StateSnapshot
    arrays: WindowArrays


def raw_window(history: SampleHistory, t_from: float, t_to: float, dt_s: float) -> RawWindow:
    """The history's samples for the grid [t_from, t_to] (s): sample times jitter around the grid, so
    the samples within half a step outside it belong to its end points (``resample_window``,
    ``FilteredState.push``) and are included."""
    half = 0.5 * dt_s
    return history.raw_window(t_from - half, t_to + half)


def job_window(job: StartJob, live: FilteredState, history: SampleHistory, config: CoreConfig) -> JobWindow:
    """The window of ``job`` from max(its start, the state's convergence time); raises ``StateConverging``
    (not converged yet), ``InsufficientWindowError`` or ``LiveStateError`` naming why not."""
    ready = live.ready_at() if live.initialized else None
    if ready is None:
        raise StateConverging(converging_reason(live))
    snap = live.field_at(max(job.t_from, ready))
    raw = raw_window(history, snap.t, job.t_to, config.rules.dt_s)
    arrays = resample_window(raw, snap.t, job.t_to, config.rules)
    return JobWindow(start=snap, arrays=arrays)


def converging_reason(live: FilteredState) -> str:
    """``state_converging: ...`` with the convergence test's figures (or why the state has not started)."""
    if not live.initialized:
        return (
            f"{STATE_CONVERGING}: the live state has not started (no sample with ambient, speed and torque)"
        )
    since = datetime.fromtimestamp(live.started_at or live.t, tz=UTC).isoformat(timespec="seconds")
    return f"{STATE_CONVERGING}: live state not converged since {since} ({live.convergence().reason})"


def job_request(
    job: StartJob,
    window: JobWindow,
    *,
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
        carry_start_error=config.carry_start_error,
        start_cov=np.array(window.start.cov) if config.carry_start_error else None,
        start_modes=config.start_modes if config.carry_start_error else 0,
        time_budget_s=config.time_budget_s,
        ci_threshold=config.ci_threshold,
        offsets_c=None if offsets is None else offsets.offsets_c,
        offset_sd_c=None if offsets is None else offsets.sd_c,
    )
