"""A speed-map identification job (``identification.mode = "speed_map"``): the worker side.

The core sends a ``JobRequest`` whose ``speed_map`` is a :class:`MapJob` (the prior: the last posterior
after ``forget``, or the family's cold-start prior); the worker (``service.identify.worker.run_job``) fits
``model.hmap_identify.identify_map`` over the request's window from the request's start field (the filtered
live state at the window start), with the calibration's offsets subtracted, and returns the ``MapFit``.

Segments: the measured per-step speed is made piecewise constant (``segment_speed``): a new segment starts
when the speed leaves the current segment's running mean by more than ``SEGMENT_TOL_RPM``, and each segment
takes its mean. Speed noise on the CAN bus would otherwise cut the window into a segment per step (the cost
is one eigendecomposition per segment).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from model.hmap_identify import MapFit
    from service.identify.window import WindowArrays
    from service.modelload import LoadedModel

__all__ = [
    "MODEL_ERROR_C",
    "SEGMENT_TOL_RPM",
    "MapJob",
    "run_map_identification",
    "segment_speed",
]

SEGMENT_TOL_RPM = 75.0
# °C, 1σ of a constant per-channel model error (model.identify.IdentifyOptions.model_error_c: the reduced
# model's and the plant's differences at the sensors)
MODEL_ERROR_C = 0.02


@dataclass(frozen=True, eq=False, kw_only=True)
class MapJob:
    """The map part of a job request: family and prior (θ mean (p,), covariance (p, p))."""

    family: Literal["nodes", "physics"]
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    start_mean: np.ndarray | None = None  # where the iteration starts (the newest map's θ; None: the prior's)


def segment_speed(speed_rpm: np.ndarray, tol_rpm: float = SEGMENT_TOL_RPM) -> np.ndarray:
    """Piecewise-constant speed (n,) [rpm]: a segment runs while |n − its running mean| <= ``tol_rpm``;
    each step gets its segment's mean."""
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    out = np.empty_like(n)
    start, total = 0, 0.0
    for k, v in enumerate(n):
        if k > start and abs(v - total / (k - start)) > tol_rpm:
            out[start:k] = total / (k - start)
            start, total = k, 0.0
        total += v
    out[start:] = total / (len(n) - start)
    return out


def run_map_identification(
    model: LoadedModel,
    window: WindowArrays,
    t0_c: float | np.ndarray,
    job: MapJob,
    offsets_c: np.ndarray | None,
    offset_sd_c: np.ndarray | None = None,
    start_cov: np.ndarray | None = None,
    start_modes: int = 0,
) -> MapFit:
    """``identify_map`` on ``window`` from the start field ``t0_c`` with ``job``'s prior; each channel's
    constant bias (the offset still unknown, 1σ ``offset_sd_c``, and the reduced model's error at the
    sensor, ``MODEL_ERROR_C``) is fitted as a nuisance and marginalised out, and so are the start state's
    ``start_modes`` leading uncertain directions of ``start_cov`` (r, r) °C² (the filtered live state's)."""
    from model.hmap import Family, Gaussian
    from model.hmap_identify import SpeedWindow, identify_map
    from model.inputs import inputs_from_operation

    ambient, speed, torque = window.step_inputs()
    inputs = inputs_from_operation(
        model.spec, dt_s=window.dt_s, speed_rpm=speed, torque_nm=torque, ambient_c=ambient
    )
    measured = np.asarray(window.measured_c, dtype=float)
    if offsets_c is not None:
        measured = measured - np.where(np.isfinite(offsets_c), offsets_c, 0.0)[None, :]
    sw = SpeedWindow(
        inputs=inputs,
        speed_rpm=segment_speed(speed),
        measured_c=measured,
        mask=np.asarray(window.mask, dtype=bool),
        t0=t0_c,
    )
    prior = Gaussian(np.asarray(job.prior_mean, dtype=float), np.asarray(job.prior_cov, dtype=float))
    sd = np.zeros(32) if offset_sd_c is None else np.nan_to_num(np.asarray(offset_sd_c, dtype=float))
    bias = np.sqrt(sd**2 + MODEL_ERROR_C**2) if job.family == "nodes" else None
    modes = None
    if start_cov is not None and start_modes > 0 and job.family == "nodes":
        lam, vec = np.linalg.eigh(0.5 * (start_cov + start_cov.T))
        top = np.argsort(lam)[::-1][:start_modes]
        modes = (vec[:, top] * np.sqrt(np.maximum(lam[top], 0.0))).T  # (K, r)
    return identify_map(model.rom, sw, prior, family=Family(job.family), bias_sd_c=bias, start_modes=modes)
