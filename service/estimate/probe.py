"""Sparse drift measurements in service: a probe's axial reading updates the mechanical posterior (pure core).

Shops probe a reference (a tool setter, a probe on an artefact) every 30–120 min; the reading is the tool's
axial position relative to the commissioned zero [µm], so it measures the served axial growth itself (no
offset of its own). Given the live field T at the reading's instant (its reduced mean over the zero), the
growth is bilinear in θ = (s, a_s, a_h) (``service.estimate.mechanics``)::

    y = Σ_m w_m(s) Σ_j c_j F[m, j] + e,   w = (1 − s, s),  c = (1, a_s, a_h)
    F = op_axial · (T − T_ref)   (2 mounts, 3 α groups) [µm]

``F`` (the fit's feature row, ``service.shell.commissioning._features``) is all a reading needs of the
field, so it is stored with the reading and the update is replayed exactly after a restart. The update is
one extended-Kalman step linearised at the current mean (exact in each of s and α separately)::

    ŷ = y(θ̂),  h = ∂y/∂θ (3,),  S = h Σ hᵀ + sd² + σ_field²,  ν = y − ŷ
    K = Σ hᵀ / S,  θ̂ ← θ̂ + K ν,  Σ ← (I − K h) Σ (I − K h)ᵀ + K (sd² + σ_field²) Kᵀ   (Joseph form)

A reading with |ν| > ``gate_sigma`` · √S (a crash or a tool change since the last one) is not absorbed.

Errors::

    ProbeError(ServiceError, ValueError)   a reading of the wrong shape or value (the field named)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.contracts.probe import ProbeError, ProbeMeasurement
from service.estimate.mechanics import PRIOR_MEAN

__all__ = [
    "PROBE_PRIOR_SD",
    "ProbeUpdate",
    "absorb",
    "predict",
    "prior_covariance",
    "replay",
]

Array = NDArray[np.float64]
# the mechanics before any test (docs/commissioning.md, "Probe measurements"): s uniform on [0, 1] (sd
# 1/√12), α factors ±5 % as 1σ (the commissioning fit's Gaussian prior, ``model.growthfit.MechanicsPrior``)
PROBE_PRIOR_SD = (1.0 / math.sqrt(12.0), 0.05, 0.05)
DEFAULT_GATE_SIGMA = 3.0


def prior_covariance() -> Array:
    """Σ_θ (3, 3) of the mechanics before any test (``PROBE_PRIOR_SD``, uncorrelated)."""
    return np.diag(np.square(PROBE_PRIOR_SD))


def prior_mean() -> Array:
    """θ (3,) before any test: s 0.5, α factors 1."""
    return np.asarray(PRIOR_MEAN, dtype=float)


def _features(features: ArrayLike) -> Array:
    f = np.asarray(features, dtype=float)
    if f.shape != (2, 3) or not np.all(np.isfinite(f)):
        raise ProbeError(f"features: expected finite (2 mounts, 3 α groups) µm, got shape {f.shape}")
    return f


def predict(features: ArrayLike, x: ArrayLike) -> tuple[float, Array]:
    """(ŷ [µm], h = ∂ŷ/∂θ (3,)) of the axial growth with feature row ``features`` (2, 3) at θ ``x``."""
    f = _features(features)
    s, a_s, a_h = (float(v) for v in np.asarray(x, dtype=float)[:3])
    c = np.array([1.0, a_s, a_h])
    g = f @ c  # growth under each mount idealisation (2,)
    w = np.array([1.0 - s, s])
    y = float(w @ g)
    h = np.array([g[1] - g[0], float(w @ f[:, 1]), float(w @ f[:, 2])])
    return y, h


@dataclass(frozen=True)
class ProbeUpdate:
    """One reading's effect: the posterior after it (``x``, ``cov``; unchanged when not accepted), the
    prediction ``predicted_um``, its 1σ ``sigma_um`` (√S), the innovation and whether it was absorbed."""

    x: Array
    cov: Array
    predicted_um: float
    sigma_um: float
    innovation_um: float
    accepted: bool


def absorb(
    x: ArrayLike,
    cov: ArrayLike,
    features: ArrayLike,
    axial_um: float,
    var_um2: float,
    *,
    gate_sigma: float | None = DEFAULT_GATE_SIGMA,
) -> ProbeUpdate:
    """One Kalman step (module docstring) of θ ``x`` (3,), Σ ``cov`` (3, 3) with a reading ``axial_um`` of
    variance ``var_um2`` (the probe's sd² plus the field's growth variance) [µm²]; not absorbed when
    |ν| > ``gate_sigma`` · √S (None: always absorbed, as a replay of readings accepted before)."""
    xv = np.asarray(x, dtype=float)
    p = np.asarray(cov, dtype=float)
    if not (math.isfinite(axial_um) and math.isfinite(var_um2) and var_um2 > 0.0):
        raise ProbeError(
            f"axial_um, variance: need finite values and a variance > 0, got {axial_um}, {var_um2}"
        )
    y_hat, h = predict(features, xv)
    s = float(h @ p @ h) + float(var_um2)
    sigma = math.sqrt(s)
    nu = float(axial_um) - y_hat
    if gate_sigma is not None and abs(nu) > gate_sigma * sigma:
        return ProbeUpdate(xv.copy(), p.copy(), y_hat, sigma, nu, False)
    k = p @ h / s
    a = np.eye(3) - np.outer(k, h)
    new_p = a @ p @ a.T + float(var_um2) * np.outer(k, k)
    return ProbeUpdate(xv + k * nu, 0.5 * (new_p + new_p.T), y_hat, sigma, nu, True)


def replay(x: ArrayLike, cov: ArrayLike, readings: list[ProbeMeasurement]) -> tuple[Array, Array]:
    """The posterior after the accepted ``readings`` (in the order given: oldest first), without gating
    (each was gated when it came)."""
    xv, p = np.asarray(x, dtype=float), np.asarray(cov, dtype=float)
    for m in readings:
        if not m.accepted:
            continue
        up = absorb(xv, p, m.features, m.axial_um, m.sd_um**2 + m.field_var_um2, gate_sigma=None)
        xv, p = up.x, up.cov
    return xv, p
