"""Sparse drift measurements in service: a probe's axial reading updates the mechanical posterior and the
fixture offset (pure core).

Shops probe a reference (a tool setter, a probe on an artefact) every 30–120 min; the reading is the tool's
axial position relative to the commissioned zero [µm]: the served axial growth plus whatever offset a
fixture or a tool holder has taken since the commissioning. Given the live field T at the reading's
instant (its reduced mean over the zero), the reading is bilinear in θ = (s, a_s, a_h)
(``service.estimate.mechanics``) plus the offset b [µm]; the state is x = (s, a_s, a_h, b)::

    y = Σ_m w_m(s) Σ_j c_j F[m, j] + b + e,   w = (1 − s, s),  c = (1, a_s, a_h)
    F = op_axial · (T − T_ref)   (2 mounts, 3 α groups) [µm]

``F`` (the fit's feature row, ``service.shell.commissioning._features``) is all a reading needs of the
field, so it is stored with the reading and the update is replayed exactly after a restart.

**Prior and time update.** θ starts from the commissioning's posterior; b from N(0, ``offset_sd_um``²) at
the commissioning's instant (b is 0 by the definition of the zero, but a fixture or tool holder may have
changed since). Between readings b is a random walk: Var(b) grows by ``offset_q_um2_per_h`` per hour; θ has
no process noise (the mechanics change only with the machine).

**Measurement update.** One extended-Kalman step linearised at the current mean (exact in each of s, α and
b separately)::

    ŷ = y(x̂),  h = ∂y/∂x = (∂y/∂θ, 1),  S = h P hᵀ + sd² + σ_field²,  ν = y − ŷ
    K = P hᵀ / S,  x̂ ← x̂ + K ν,  P ← (I − K h) P (I − K h)ᵀ + K (sd² + σ_field²) Kᵀ   (Joseph form)

**Identifiability.** b enters every reading with weight 1; the mount s through F[1] − F[0], which scales
with the field, and the α factors through their group's share of it. A constant offset and a changed mount
therefore separate once readings are taken at different thermal states (a cold and a warm spindle); with
readings at one state only they stay correlated in P, the served growth at that state is right, and the
cross covariance is carried into the served CI.

**Gate and persistent offsets.** A reading with |ν| > ``gate_sigma`` · √S is not absorbed: a crash, a
chip under the setter, a mis-read. A step of the offset (a fixture re-clamped, another tool holder) gives
the same symptom, but persistently; a smaller step (2–3 σ) is absorbed, but a Kalman gain tuned for a slow
b follows it over many readings and leans on θ meanwhile. So, a two-reading persistence test: when a reading
lies beyond ``step_sigma`` · √S (< ``gate_sigma``) and so did the reading immediately before it, with a
*consistent* innovation — the same sign and |ν₂ − ν₁| ≤ ``gate_sigma`` · √(S₁ + S₂) — the pair is taken as a
step of b: b's variance is re-initialised to ``offset_sd_um``² (its cross covariances with θ zeroed, its mean
kept) and the second reading is absorbed, gated or not. One outlier is never absorbed (a single reading
never makes a step); a persistent step is tracked from its second reading on; θ is not bent by it, because
after the re-initialisation b carries nearly all of the innovation (Var(b) ≫ h_θ P_θθ h_θᵀ). A false step
needs two same-signed readings beyond 2 σ in a row (≈ 0.1 % of pairs) and costs only b's precision until
the next reading. The step is stored with the reading (``offset_step``); a gated first reading of the pair
stays stored as not absorbed.

**Replay.** ``replay`` takes the stored decisions (``accepted``, ``offset_step``) instead of re-running the
gate: the accepted readings, oldest first, each after b's time update since the previous accepted one (a
random walk with no other dynamics: one update over the whole gap equals one per reading in between) and
b's re-initialisation where the reading was a step; the live posterior and the replayed one are the same
numbers. Readings stored before the offset existed (no ``offset_step``: false) replay into the same model.

Errors::

    ProbeError(ServiceError, ValueError)   a reading of the wrong shape or value (the field named)
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.contracts.probe import ProbeError, ProbeMeasurement
from service.estimate.mechanics import PRIOR_MEAN

__all__ = [
    "DEFAULT_GATE_SIGMA",
    "PROBE_PRIOR_SD",
    "ProbeState",
    "ProbeTuning",
    "ProbeUpdate",
    "absorb",
    "consistent_step",
    "predict",
    "prior_covariance",
    "replay",
    "replay_state",
    "start_state",
    "take_reading",
]

Array = NDArray[np.float64]
# the mechanics before any test (docs/commissioning.md, "Probe measurements"): s uniform on [0, 1] (sd
# 1/√12), α factors ±5 % as 1σ (the commissioning fit's Gaussian prior, ``model.growthfit.MechanicsPrior``)
PROBE_PRIOR_SD = (1.0 / math.sqrt(12.0), 0.05, 0.05)
DEFAULT_GATE_SIGMA = 3.0
N_MECH = 3  # θ = (s, a_s, a_h); the offset b is state N_MECH
B = N_MECH


def prior_covariance() -> Array:
    """Σ_θ (3, 3) of the mechanics before any test (``PROBE_PRIOR_SD``, uncorrelated)."""
    return np.diag(np.square(PROBE_PRIOR_SD))


def prior_mean() -> Array:
    """θ (3,) before any test: s 0.5, α factors 1."""
    return np.asarray(PRIOR_MEAN, dtype=float)


@dataclass(frozen=True, kw_only=True)
class ProbeTuning:
    """The probe filter's settings (``[compensation]`` ``probe_*``; declared there): the gate [σ], the step
    test's threshold [σ], b's prior 1σ at the commissioning and after a step [µm], b's random walk [µm²/h]."""

    gate_sigma: float
    step_sigma: float
    offset_sd_um: float
    offset_q_um2_per_h: float


def _features(features: ArrayLike) -> Array:
    f = np.asarray(features, dtype=float)
    if f.shape != (2, 3) or not np.all(np.isfinite(f)):
        raise ProbeError(f"features: expected finite (2 mounts, 3 α groups) µm, got shape {f.shape}")
    return f


def predict(features: ArrayLike, x: ArrayLike) -> tuple[float, Array]:
    """(ŷ [µm], h = ∂ŷ/∂x) of the reading with feature row ``features`` (2, 3) at the state ``x``: θ (3,),
    h (3,); or θ and the offset b (4,), then ŷ includes b and h (4,) ends with 1."""
    f = _features(features)
    xv = np.asarray(x, dtype=float)
    s, a_s, a_h = (float(v) for v in xv[:N_MECH])
    c = np.array([1.0, a_s, a_h])
    g = f @ c  # growth under each mount idealisation (2,)
    w = np.array([1.0 - s, s])
    y = float(w @ g)
    h = [g[1] - g[0], float(w @ f[:, 1]), float(w @ f[:, 2])]
    if xv.size > N_MECH:
        y += float(xv[B])
        h.append(1.0)
    return y, np.array(h)


@dataclass(frozen=True)
class ProbeUpdate:
    """One reading's effect: the posterior after it (``x``, ``cov``; unchanged when not accepted), the
    prediction ``predicted_um``, its 1σ ``sigma_um`` (√S), the innovation, whether it was absorbed and
    whether as a step of the offset (the gate's numbers are then those before the re-initialisation)."""

    x: Array
    cov: Array
    predicted_um: float
    sigma_um: float
    innovation_um: float
    accepted: bool
    offset_step: bool = False


def absorb(
    x: ArrayLike,
    cov: ArrayLike,
    features: ArrayLike,
    axial_um: float,
    var_um2: float,
    *,
    gate_sigma: float | None = DEFAULT_GATE_SIGMA,
) -> ProbeUpdate:
    """One Kalman step (module docstring) of the state ``x`` (θ (3,), or θ and b (4,)), P ``cov`` with a
    reading ``axial_um`` of variance ``var_um2`` (the probe's sd² plus the field's growth variance) [µm²];
    not absorbed when |ν| > ``gate_sigma`` · √S (None: always absorbed, as a replay)."""
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
    a = np.eye(xv.size) - np.outer(k, h)
    new_p = a @ p @ a.T + float(var_um2) * np.outer(k, k)
    return ProbeUpdate(xv + k * nu, 0.5 * (new_p + new_p.T), y_hat, sigma, nu, True)


@dataclass(frozen=True)
class ProbeState:
    """The probe filter's state: x = (s, a_s, a_h, b) (4,), P (4, 4), ``t`` [epoch s] of its last time
    update (the commissioning, then the last absorbed reading), ``absorbed`` readings since the
    commissioning, ``steps`` of them absorbed as a step of the offset, and ``pending`` (ν, √S) of the last
    reading when it lay beyond ``step_sigma`` (None: within, a step, or none)."""

    x: Array
    cov: Array
    t: float
    absorbed: int = 0
    steps: int = 0
    pending: tuple[float, float] | None = None

    @property
    def mechanics(self) -> tuple[Array, Array]:
        """θ (3,) and Σ_θ (3, 3)."""
        return self.x[:N_MECH].copy(), self.cov[:N_MECH, :N_MECH].copy()

    @property
    def offset(self) -> tuple[float, float, Array]:
        """b [µm], Var(b) [µm²] and Cov(θ, b) (3,) [µm]."""
        return float(self.x[B]), float(self.cov[B, B]), self.cov[:N_MECH, B].copy()


def start_state(mean: ArrayLike, cov: ArrayLike, t: float, tuning: ProbeTuning) -> ProbeState:
    """The filter at the commissioning (θ ``mean`` (3,), Σ_θ ``cov`` (3, 3), instant ``t`` [epoch s]) with
    b ~ N(0, ``offset_sd_um``²) uncorrelated with θ."""
    x = np.append(np.asarray(mean, dtype=float)[:N_MECH], 0.0)
    p = np.zeros((N_MECH + 1, N_MECH + 1))
    p[:N_MECH, :N_MECH] = np.asarray(cov, dtype=float)[:N_MECH, :N_MECH]
    p[B, B] = tuning.offset_sd_um**2
    return ProbeState(x, p, float(t))


def _time_update(state: ProbeState, t: float, tuning: ProbeTuning) -> Array:
    """P at ``t`` [epoch s]: b's random walk since ``state.t`` (none backwards)."""
    p = state.cov.copy()
    p[B, B] += tuning.offset_q_um2_per_h * max(float(t) - state.t, 0.0) / 3600.0
    return p


def _offset_reset(p: Array, tuning: ProbeTuning) -> Array:
    """P with b re-initialised: Var(b) = ``offset_sd_um``², Cov(θ, b) = 0."""
    q = p.copy()
    q[B, :] = 0.0
    q[:, B] = 0.0
    q[B, B] = tuning.offset_sd_um**2
    return q


def _beyond(nu: float, sigma: float, threshold: float) -> bool:
    return abs(nu) > threshold * sigma


def consistent_step(
    pending: tuple[float, float] | None, nu: float, sigma: float, tuning: ProbeTuning
) -> bool:
    """True when a reading (ν, √S) beyond ``step_sigma`` confirms the one before it (``pending``, beyond it
    too): the same sign and |ν − ν₁| ≤ ``gate_sigma`` · √(S₁ + S) (module docstring)."""
    if pending is None or not _beyond(nu, sigma, tuning.step_sigma):
        return False
    nu1, sigma1 = pending
    return nu * nu1 > 0.0 and abs(nu - nu1) <= tuning.gate_sigma * math.hypot(sigma, sigma1)


def _pending(nu: float, sigma: float, tuning: ProbeTuning) -> tuple[float, float] | None:
    return (nu, sigma) if _beyond(nu, sigma, tuning.step_sigma) else None


def take_reading(
    state: ProbeState,
    features: ArrayLike,
    axial_um: float,
    var_um2: float,
    t: float,
    tuning: ProbeTuning,
) -> tuple[ProbeState, ProbeUpdate]:
    """A live reading at ``t`` [epoch s] (module docstring): absorbed; gated; or, beyond ``step_sigma`` right
    after a consistent one, absorbed as a step of the offset. The new state and the reading's outcome."""
    p = _time_update(state, t, tuning)
    up = absorb(state.x, p, features, axial_um, var_um2, gate_sigma=tuning.gate_sigma)
    pending = _pending(up.innovation_um, up.sigma_um, tuning)
    if consistent_step(state.pending, up.innovation_um, up.sigma_um, tuning):
        step = absorb(state.x, _offset_reset(p, tuning), features, axial_um, var_um2, gate_sigma=None)
        out = replace(up, x=step.x, cov=step.cov, accepted=True, offset_step=True)
        return ProbeState(step.x, step.cov, float(t), state.absorbed + 1, state.steps + 1), out
    if up.accepted:
        return ProbeState(up.x, up.cov, float(t), state.absorbed + 1, state.steps, pending), up
    return replace(state, pending=pending), up


def replay_state(state: ProbeState, readings: Iterable[ProbeMeasurement], tuning: ProbeTuning) -> ProbeState:
    """``state`` after the stored ``readings`` (oldest first) with their stored decisions, no gate (module
    docstring, "Replay"); a reading not absorbed only sets ``pending``."""
    for m in readings:
        pending = None if m.offset_step else _pending(m.innovation_um, m.sigma_um, tuning)
        if not m.accepted:
            state = replace(state, pending=pending)
            continue
        t = m.at.timestamp()
        p = _time_update(state, t, tuning)
        if m.offset_step:
            p = _offset_reset(p, tuning)
        var = m.sd_um**2 + m.field_var_um2
        up = absorb(state.x, p, m.features, m.axial_um, var, gate_sigma=None)
        state = ProbeState(up.x, up.cov, t, state.absorbed + 1, state.steps + int(m.offset_step), pending)
    return state


def replay(x: ArrayLike, cov: ArrayLike, readings: list[ProbeMeasurement]) -> tuple[Array, Array]:
    """θ's posterior (3-state, no offset) after the accepted ``readings`` (oldest first), without gating
    (each was gated when it came): the mechanics alone, as before the offset state."""
    xv, p = np.asarray(x, dtype=float), np.asarray(cov, dtype=float)
    for m in readings:
        if not m.accepted:
            continue
        up = absorb(xv, p, m.features, m.axial_um, m.sd_um**2 + m.field_var_um2, gate_sigma=None)
        xv, p = up.x, up.cov
    return xv, p
