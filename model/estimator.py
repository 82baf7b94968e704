"""Closed-loop live state: a Kalman filter on the reduced model's coordinates (pure numpy/scipy).

The reduced model (``model.rom``) has an E-orthonormal basis V (N, r), so T ≈ V·a, E_r = I, and its step over
one sample with the inputs held (docs/design/rom.md) is, with K_r(H) = Φ·diag(λ)·Φᵀ,

    a⁺ = A·a + G·z_r,   A = Φ·diag(μ)·Φᵀ,  G = Φ·diag(γ)·Φᵀ,  z_r = T_amb·Σ H_i·z_i,r + Q_f·q_f,r + Q_r·q_r,r

with μ, γ = ``model.rom_modal.step_factors(λ, Δt, θ, rom.substeps)``: the same step as the served reduced
model (``substeps`` 0: exact with the input held over the step; s ≥ 1: s θ-steps), so with no measurement
the filter's mean *is* the open-loop reduced trajectory.
The measurement of the 32 channels is y = C·a + v (C = ``rom.sensors``). Each sample runs the linear Kalman
filter (Kalman 1960; Simon, *Optimal State Estimation*, 2006, ch. 5): predict mean and covariance with A
and the process noise Q, then update with the sample's usable channels only (mask, finite values), after
subtracting the per-channel offsets. The covariance update is Joseph's form (stays symmetric positive
semi-definite).

Process noise (``NoiseModel``; docs/design/estimator.md for the figures). The errors of H and of the bearing
heats are persistent, not white: treated as white noise per step they left the filter 3–4× overconfident
(sensor error 0.05–0.07 °C against a claimed 1σ of 0.016 °C with H 30 % off). They are therefore *considered*
parameters (Schmidt–Kalman or "consider" filter, Schmidt 1966; Simon 2006): relative errors p (9,) of
H1..H7, Q_f, Q_r with zero mean and 1σ ``h_rel``, ``load_rel``, first-order Gauss–Markov in time (correlation
time ``param_tau_s``), whose effect on the step a⁺ = A·a + G·z_r + J·p is linearised about the mean
before the step (exactly: A and G are matrix functions of K_r, differentiated with Daleckii–Krein divided
differences, ``model.rom_segments.loewner``),

    ∂a⁺/∂p_i = H_i·(T_amb·G·z_i,r + Φ·((L_μ ∘ K̃_i)·Φᵀ·a + (L_γ ∘ K̃_i)·Φᵀ·z_r)),   K̃_i = Φᵀ·K_i,r·Φ,
    ∂a⁺/∂p_Q = G·q_r·Q,

and whose covariance with the state (``Estimate.cross``) is carried; they are never estimated (gain 0: the
identification estimates H). White parts: the ambient's error (``ambient_c`` [°C]) and the reduced model's
one-step defect vs the full FE (``model_cov``, ``model.estimator_noise.rom_defect_cov``).

Measurement noise R = (σ_meas² + σ_model²)·I over the used channels: the DAQ's noise plus the model's error
at the sensors that does not live in the reduced state (mesh and ROM error; default 0.02 °C). σ_meas comes
from a setting or from the innovations (``matched_sigma_c``, covariance matching).

State: only a. No augmentation: a uniform offset of the field is already a state direction (the uniform
field is the first basis vector), and per-channel offsets come from calibration (``offsets_c``).

Changing the considered parameters' 1σ (``StateEstimator.set_noise``, e.g. a new H with a narrower CI)
rescales their cross-covariance with the state (``rescale_cross``): the joint covariance [[P, X], [Xᵀ, Σ]]
must stay positive semi-definite, or the prediction's P⁺ = A·P·Aᵀ + A·X·Jᵀ + J·Xᵀ·Aᵀ + J·Σ·Jᵀ is not a
covariance (docs/design/estimator.md, "Covariance health"). Every predicted and updated covariance is checked
(``check_covariance``): a non-finite mean, a negative or non-finite variance or a non-PSD covariance raises
``CovarianceError`` and leaves the belief as it was.

Errors::

    EstimatorError(ModelError, ValueError)   a bad argument (shape, non-finite, H <= 0, dt <= 0); the field
                                             is named
      CovarianceError                        the belief stopped being a distribution (non-finite, negative
                                             variance, not positive semi-definite): restart from a prior
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack
from scipy.stats import chi2

from model.errors import ModelError
from model.rom_modal import step_factors
from model.rom_segments import loewner, step_derivatives

Array = NDArray[np.float64]
N_H = 7
N_CHANNELS = 32
N_PARAMS = N_H + 2  # considered parameter errors: H1..H7, front and rear bearing heat


class EstimatorError(ModelError, ValueError):
    """A bad argument to the state estimator; the message names the field."""


class CovarianceError(EstimatorError):
    """The filter's belief is no longer a distribution: a non-finite mean or covariance, a negative variance
    or a covariance that is not positive semi-definite. The belief must not be served; restart from a
    prior."""


@dataclass(frozen=True, eq=False)
class NoiseModel:
    """Noise levels of the filter (1σ).

    ``sigma_meas_c`` [°C] the DAQ's noise per channel; ``sigma_model_c`` [°C] the model's error at the sensors
    outside the reduced state (added to R); ``h_rel`` relative error of each H (a scalar or 7 values);
    ``load_rel`` relative error of each bearing heat; ``param_tau_s`` [s] correlation time of these parameter
    errors (first-order Gauss–Markov; ``inf``: a constant bias); ``ambient_c`` [°C] white error of each step's
    ambient; ``model_cov`` (r, r) [°C², reduced coordinates, per step] the reduced model's one-step defect vs
    the full FE (``model.estimator_noise``; None: left out).
    """

    sigma_meas_c: float = 0.15
    sigma_model_c: float = 0.02
    h_rel: float | tuple[float, ...] = 0.2
    load_rel: float = 0.1
    param_tau_s: float = 1800.0
    ambient_c: float = 0.0
    model_cov: Array | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_meas_c) and self.sigma_meas_c > 0.0):
            raise EstimatorError(f"noise.sigma_meas_c: must be > 0 °C, got {self.sigma_meas_c!r}")
        for name in ("sigma_model_c", "load_rel", "ambient_c"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise EstimatorError(f"noise.{name}: must be finite and >= 0, got {value!r}")
        h = np.asarray(self.h_rel, dtype=np.float64)
        if h.shape not in ((), (N_H,)) or not np.all(np.isfinite(h)) or np.any(h < 0.0):
            raise EstimatorError(f"noise.h_rel: expected one or {N_H} finite values >= 0, got {self.h_rel!r}")
        if not self.param_tau_s > 0.0:
            raise EstimatorError(
                f"noise.param_tau_s: must be > 0 s (inf: constant), got {self.param_tau_s!r}"
            )

    @property
    def r_var(self) -> float:
        """Measurement variance per channel [°C²]."""
        return float(self.sigma_meas_c**2 + self.sigma_model_c**2)

    @cached_property
    def param_var(self) -> Array:
        """``param_std`` squared (9,) (cached: used every step)."""
        return np.asarray(self.param_std() ** 2)

    def param_std(self) -> Array:
        """1σ of the considered parameters (9,): relative errors of H1..H7, front and rear heat."""
        h = np.broadcast_to(np.asarray(self.h_rel, dtype=np.float64), (N_H,))
        return np.concatenate([h, [self.load_rel, self.load_rel]])

    def param_rho(self, dt_s: float) -> float:
        """Step correlation exp(−Δt/τ) of the parameter errors."""
        return float(np.exp(-dt_s / self.param_tau_s)) if np.isfinite(self.param_tau_s) else 1.0


@dataclass(frozen=True)
class StepInput:
    """Inputs held over one step (the sample before → this sample): H (7,) [W/(m²·K)], ambient [°C], front
    and rear bearing heat [W], step Δt [s]."""

    h: Array
    ambient_c: float
    q_front_w: float
    q_rear_w: float
    dt_s: float = 10.0


@dataclass(frozen=True, eq=False)
class Estimate:
    """The filter's belief: mean (r,) and covariance (r, r) of the reduced state a (T ≈ V·a) [°C, °C²], and
    ``cross`` (r, 9): the state error's covariance with the considered parameter errors (``NoiseModel``)."""

    mean: Array
    cov: Array
    cross: Array


@dataclass(frozen=True, eq=False)
class StepResult:
    """One sample: the posterior ``estimate``; the ``innovation`` y − C·a⁻ (32,) [°C], NaN where not used;
    ``nis`` = νᵀS⁻¹ν over the ``dof`` used channels (0 and 0 when none was used); ``predicted_c`` C·a⁻ (32,)
    and ``predicted_std_c`` √diag(S) (32,) [°C], the prediction the sample was checked against."""

    estimate: Estimate
    innovation: Array
    nis: float
    dof: int
    predicted_c: Array
    predicted_std_c: Array


@dataclass(frozen=True, eq=False)
class Transition:
    """The reduced model's step for fixed H and Δt: a⁺ = A·a + G·z_r, with the load directions
    G·(Σ H_i z_i,r) per °C ambient, G·q_f,r and G·q_r,r per W; for the parameter Jacobian the eigenvectors
    ``phi`` of K_r(H), the zones' loads G·z_i,r (r, 7) and the divided-difference weighted zone conductances
    L_μ ∘ K̃_i and L_γ ∘ K̃_i (7, r, r) (``param_jacobian``)."""

    h: Array
    dt_s: float
    a: Array
    g: Array
    per_ambient: Array
    per_front: Array
    per_rear: Array
    phi: Array
    zone_loads: Array
    d_mu: Array
    d_gamma: Array


# a covariance's smallest eigenvalue may be this far below 0, relative to its largest variance (round-off:
# measured ~1e-19 on healthy runs of the default model, r = 46)
PSD_REL_TOL = 1e-9


def check_covariance(est: Estimate, *, rel_tol: float = PSD_REL_TOL) -> None:
    """Raise ``CovarianceError`` unless ``est`` is a distribution: finite mean, cov and cross, every variance
    ≥ 0 and cov positive semi-definite up to ``rel_tol`` × its largest variance (one Cholesky factorisation
    of cov + tol·I, ~15 µs at r = 56). The message names what failed."""
    cov = est.cov
    # one sum per array: NaN or ±inf anywhere makes it non-finite (cheaper than isfinite over every entry)
    if not np.isfinite(float(est.mean.sum()) + float(cov.sum()) + float(est.cross.sum())):
        raise CovarianceError("state estimate: non-finite mean, covariance or cross-covariance")
    diag = np.diagonal(cov)
    scale = float(diag.max()) if diag.size else 0.0
    tol = rel_tol * max(scale, np.finfo(np.float64).tiny)
    if diag.min() < -tol:
        i = int(np.argmin(diag))
        raise CovarianceError(f"state covariance: negative variance {diag[i]:.3g} at reduced coordinate {i}")
    shifted = cov.copy()
    shifted.flat[:: cov.shape[0] + 1] += tol
    _, info = lapack.dpotrf(shifted, lower=1, clean=0, overwrite_a=1)
    if info != 0:
        low = float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[0])
        raise CovarianceError(
            f"state covariance: not positive semi-definite (smallest eigenvalue {low:.3g}, largest variance "
            f"{scale:.3g})"
        )


def rescale_cross(est: Estimate, old_std: ArrayLike, new_std: ArrayLike) -> Estimate:
    """The belief with the considered parameters' 1σ changed from ``old_std`` to ``new_std`` (9,) [relative]:
    each column of the cross-covariance X scaled by new/old (0 where old is 0), so the parameters keep their
    correlation with the state's error. The joint covariance [[P, X], [Xᵀ, Σ]] is transformed by
    diag(I, new/old) on both sides and stays positive semi-definite; keeping X with a smaller Σ does not
    (X·Σ⁻¹·Xᵀ may exceed P, and the next prediction's P is then indefinite)."""
    old = np.asarray(old_std, dtype=np.float64)
    new = np.asarray(new_std, dtype=np.float64)
    if old.shape != (N_PARAMS,) or new.shape != (N_PARAMS,):
        raise EstimatorError(f"rescale_cross: expected {N_PARAMS} values of 1σ, got {old.shape}, {new.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(old > 0.0, new / old, 0.0)
    if np.all(factor == 1.0):
        return est
    return Estimate(est.mean, est.cov, est.cross * factor[None, :])


def _check_h(h: ArrayLike) -> Array:
    arr = np.asarray(h, dtype=np.float64)
    if arr.shape != (N_H,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
        raise EstimatorError(f"h: expected {N_H} finite values > 0 W/(m²·K), got {arr!r}")
    return arr


def transition(rom: Any, h: ArrayLike, dt_s: float) -> Transition:
    """The reduced model's step (A, G, the load directions and the parameter-derivative terms) for H (7,)
    and Δt [s], with the ROM's own integration (``rom.substeps``, ``model.rom_modal.step_factors``)."""
    h_arr = _check_h(h)
    dt = float(dt_s)
    if not np.isfinite(dt) or dt <= 0.0:
        raise EstimatorError(f"dt_s: must be > 0 s, got {dt_s!r}")
    r = int(rom.k0.shape[0])
    kr = rom.k0 + (h_arr @ rom.k_zone.reshape(N_H, r * r)).reshape(r, r)
    lam, phi = np.linalg.eigh(kr)
    theta, substeps = float(rom.theta), int(getattr(rom, "substeps", 1))
    mu, gamma = step_factors(lam, dt, theta, substeps)
    dmu, dgamma = step_derivatives(lam, dt, theta, substeps)
    a = (phi * mu) @ phi.T
    g = (phi * gamma) @ phi.T
    k_modal = phi.T[None, :, :] @ rom.k_zone @ phi[None, :, :]  # (7, r, r): Φᵀ·K_i,r·Φ
    return Transition(
        h_arr,
        dt,
        a,
        g,
        g @ (h_arr @ rom.z_zone),
        g @ rom.q_front,
        g @ rom.q_rear,
        phi,
        g @ rom.z_zone.T,
        loewner(lam, mu, dmu)[None] * k_modal,
        loewner(lam, gamma, dgamma)[None] * k_modal,
    )


def predict_mean(tr: Transition, mean: Array, u: StepInput) -> Array:
    """The reduced state after one step [°C, reduced]: A·a + G·z_r."""
    return np.asarray(
        tr.a @ mean + u.ambient_c * tr.per_ambient + u.q_front_w * tr.per_front + u.q_rear_w * tr.per_rear
    )


def param_jacobian(rom: Any, tr: Transition, u: StepInput, prior: Array) -> Array:
    """∂a⁺/∂p (r, 9) per unit relative error p of H1..H7, Q_f, Q_r at the mean ``prior`` before the step:
    H_i·(T_amb·G·z_i,r + Φ·((L_μ ∘ K̃_i)·Φᵀ·a + (L_γ ∘ K̃_i)·Φᵀ·z_r)) and G·q·Q (exact derivative of the
    step; ``Transition``)."""
    load = u.ambient_c * (tr.h @ rom.z_zone) + u.q_front_w * rom.q_front + u.q_rear_w * rom.q_rear
    b, c = tr.phi.T @ prior, tr.phi.T @ load
    modal = tr.d_mu @ b + tr.d_gamma @ c  # (7, r)
    per_h = (u.ambient_c * tr.zone_loads + tr.phi @ modal.T) * tr.h[None, :]
    return np.concatenate(
        [per_h, (tr.per_front * u.q_front_w)[:, None], (tr.per_rear * u.q_rear_w)[:, None]], 1
    )


def white_cov(tr: Transition, noise: NoiseModel) -> Array | None:
    """The white part of Q (r, r) [°C²]: ambient error and the reduced model's defect (None: zero)."""
    q = noise.model_cov
    if noise.ambient_c > 0.0:
        amb = (noise.ambient_c**2) * np.outer(tr.per_ambient, tr.per_ambient)
        q = amb if q is None else q + amb
    return q


def predict(rom: Any, tr: Transition, est: Estimate, u: StepInput, noise: NoiseModel) -> Estimate:
    """Predict with the considered parameter errors p (Schmidt–Kalman): a⁺ = A·a + G·z_r + J·p with
    E[p] = 0, p⁺ = ρ·p + w (stationary covariance Σ = diag(``param_std``²)), so
    P⁺ = A·P·Aᵀ + A·X·Jᵀ + J·Xᵀ·Aᵀ + J·Σ·Jᵀ (+ white Q) and X⁺ = ρ·(A·X + J·Σ)."""
    mean = predict_mean(tr, est.mean, u)
    jac = param_jacobian(rom, tr, u, est.mean)
    sigma = noise.param_var
    ax = tr.a @ est.cross
    axj = ax @ jac.T
    cov = tr.a @ est.cov @ tr.a.T + axj + axj.T + (jac * sigma[None, :]) @ jac.T
    white = white_cov(tr, noise)
    if white is not None:
        cov = cov + white
    cross = noise.param_rho(tr.dt_s) * (ax + jac * sigma[None, :])
    return Estimate(mean, 0.5 * (cov + cov.T), cross)


def usable(measured: Array, mask: ArrayLike | None) -> NDArray[np.bool_]:
    """Channels used in an update: in ``mask`` (True = usable; None: all) and finite."""
    m = np.ones(measured.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != measured.shape:
        raise EstimatorError(f"mask: expected shape {measured.shape}, got {m.shape}")
    return np.asarray(m & np.isfinite(measured))


def update(
    sensors: Array, est: Estimate, measured: Array, use: NDArray[np.bool_], r_var: float
) -> tuple[Estimate, Array, float, Array]:
    """Kalman update with the channels ``use`` (Joseph form; the considered parameters get no gain): returns
    the posterior, the innovation over those channels, the NIS νᵀS⁻¹ν and diag(S) (all channels, [°C²])."""
    c_all = sensors
    pc_all = est.cov @ c_all.T  # (r, 32)
    s_diag = np.einsum("cr,rc->c", c_all, pc_all) + r_var
    if not use.any():
        return est, np.zeros(0), 0.0, s_diag
    c = c_all[use]
    pc = pc_all[:, use]
    s = c @ pc + r_var * np.eye(c.shape[0])
    nu = measured[use] - c @ est.mean
    # one LAPACK solve for the gain K = P·Cᵀ·S⁻¹ (r, m) and S⁻¹·ν (numpy's gesv: far less call overhead)
    sol = np.linalg.solve(s, np.concatenate([pc.T, nu[:, None]], axis=1))
    gain = sol[:, :-1].T
    nis = float(nu @ sol[:, -1])
    mean = est.mean + gain @ nu
    ikc = np.eye(est.mean.size) - gain @ c
    cov = ikc @ est.cov @ ikc.T + r_var * (gain @ gain.T)  # Joseph form
    # Schmidt: the parameters get no gain, their covariance with the state follows the state's correction
    return Estimate(mean, 0.5 * (cov + cov.T), ikc @ est.cross), nu, nis, s_diag


def wide_prior(
    rom: Any, *, ambient_c: float, sigma_uniform_c: float = 5.0, sigma_shape_c: float = 5.0
) -> Estimate:
    """A wide prior for a restart: the uniform field at ``ambient_c`` [°C], with 1σ ``sigma_uniform_c`` [°C]
    of a uniform offset plus an isotropic part in the reduced coordinates (correlation V·Vᵀ: the ROM's own
    smooth fields) scaled so that its 1σ averaged over the 32 sensors is ``sigma_shape_c`` [°C]."""
    if not (np.isfinite(ambient_c) and sigma_uniform_c >= 0.0 and sigma_shape_c >= 0.0):
        raise EstimatorError("wide_prior: ambient_c must be finite and the sigmas >= 0 °C")
    u = uniform_state(rom)
    r = u.size
    sens = np.asarray(rom.sensors)
    per_unit = float(np.mean(np.sum(sens * sens, axis=1)))  # mean diag(C·I·Cᵀ)
    cov = sigma_uniform_c**2 * np.outer(u, u) + (sigma_shape_c**2 / per_unit) * np.eye(r)
    return Estimate(ambient_c * u, cov, np.zeros((r, N_PARAMS)))


def heated_prior(
    rom: Any,
    *,
    ambient_c: float,
    sigma_uniform_c: float = 5.0,
    q_max_w: tuple[float, float] = (300.0, 150.0),
    sigma_shape_c: float = 0.1,
    samples: int = 256,
    seed: int = 0,
) -> Estimate:
    """A wide prior for a restart whose shape is physical: mean the uniform field at ``ambient_c`` [°C];
    covariance the second moment of the heated fields the spindle can be in, the steady states' rise above
    the ambient for ``samples`` random H (log-uniform in ``rom.h_box``) and bearing heats (uniform in
    0..``q_max_w`` [W]) (a warm spindle is roughly a fraction of such a field), plus 1σ ``sigma_uniform_c``
    [°C] of a uniform offset and an isotropic part scaled like ``wide_prior``'s to ``sigma_shape_c`` [°C] at
    the sensors (transient shapes). Unlike ``wide_prior``'s isotropic shape, the unmeasured interior is
    tied to the measured surface as the heat paths tie them, so a few samples pin the whole field."""
    if not (np.isfinite(ambient_c) and sigma_uniform_c >= 0.0 and sigma_shape_c >= 0.0 and samples > 0):
        raise EstimatorError("heated_prior: ambient_c must be finite, the sigmas >= 0 °C, samples > 0")
    rng = np.random.default_rng(seed)
    lo, hi = (float(x) for x in getattr(rom, "h_box", (5.0, 200.0)))
    h = np.exp(rng.uniform(np.log(lo), np.log(hi), (samples, N_H)))
    q = rng.uniform(0.0, 1.0, (samples, 2)) * np.asarray(q_max_w, dtype=np.float64)
    r = int(rom.k0.shape[0])
    kr = rom.k0[None] + (h @ rom.k_zone.reshape(N_H, r * r)).reshape(samples, r, r)
    rise = np.linalg.solve(kr, (q[:, :1] * rom.q_front + q[:, 1:] * rom.q_rear)[..., None])[..., 0]
    base = wide_prior(rom, ambient_c=ambient_c, sigma_uniform_c=sigma_uniform_c, sigma_shape_c=sigma_shape_c)
    cov = base.cov + rise.T @ rise / samples
    return Estimate(base.mean, 0.5 * (cov + cov.T), base.cross)


def uniform_state(rom: Any) -> Array:
    """The reduced coordinates (r,) of the uniform 1 °C field (exact: it is in the basis)."""
    return np.asarray(rom.basis_t_mass.sum(axis=1))


def field_std(basis: Array, cov: Array) -> Array:
    """1σ [°C] per row of ``basis`` (nodes (N, r) or sensors (32, r)): √diag(B·P·Bᵀ), O(N·r²)."""
    var = np.einsum("nr,nr->n", basis @ cov, basis)
    return np.asarray(np.sqrt(np.maximum(var, 0.0)))


def matched_sigma_c(innovations: ArrayLike, predicted_std_c: ArrayLike, r_var: float) -> float:
    """Online estimate of the measurement noise 1σ [°C] by covariance matching (Mehra 1972): over a run of
    samples (n, 32) of ``StepResult.innovation`` (NaN: unused) and ``predicted_std_c``, E[ν²] = C·P⁻·Cᵀ + R,
    so R ≈ mean(ν² − (S_cc − ``r_var``)). Needs a filter whose P⁻ is about right (after convergence)."""
    nu = np.asarray(innovations, dtype=np.float64)
    s = np.asarray(predicted_std_c, dtype=np.float64)
    if nu.shape != s.shape:
        raise EstimatorError(f"predicted_std_c: expected shape {nu.shape}, got {s.shape}")
    ok = np.isfinite(nu) & np.isfinite(s)
    if not ok.any():
        raise EstimatorError("innovations: no finite value")
    excess = nu[ok] ** 2 - (s[ok] ** 2 - float(r_var))
    return float(np.sqrt(max(float(np.mean(excess)), 0.0)))


@dataclass(frozen=True)
class Convergence:
    """The convergence test's verdict, with the figures it was made on."""

    converged: bool
    reason: str
    sensor_std_max_c: float
    field_rms_std_c: float
    nis_sum: float
    nis_dof: int
    nis_band: tuple[float, float]
    nis_low: bool = False  # Σ NIS below the band: cautious, not an error (does not block convergence)


@lru_cache(maxsize=256)
def chi2_band(dof: int, alpha: float) -> tuple[float, float]:
    """Two-sided (1 − alpha) region of a χ²(dof) variable ((0, inf) for dof 0); cached (scipy's ppf is
    slow)."""
    if dof <= 0:
        return (0.0, float("inf"))
    return float(chi2.ppf(alpha / 2, dof)), float(chi2.ppf(1.0 - alpha / 2, dof))


class NisWindow:
    """The last ``size`` samples' NIS and degrees of freedom; under a consistent filter their sum is
    χ²(Σ dof) (innovations are white), so ``band`` is the two-sided (1 − ``alpha``) acceptance region."""

    def __init__(self, size: int = 30, *, alpha: float = 0.01) -> None:
        if size < 1 or not 0.0 < alpha < 1.0:
            raise EstimatorError(f"NisWindow: size must be >= 1 and 0 < alpha < 1, got {size}, {alpha}")
        self.size, self.alpha = int(size), float(alpha)
        self._items: deque[tuple[float, int]] = deque(maxlen=self.size)

    def push(self, nis: float, dof: int) -> None:
        """Add one sample's NIS and the number of channels it used."""
        if dof > 0:
            self._items.append((float(nis), int(dof)))

    @property
    def count(self) -> int:
        """Samples with measurements in the window."""
        return len(self._items)

    @property
    def full(self) -> bool:
        """Whether the window holds ``size`` samples with measurements."""
        return len(self._items) == self.size

    def totals(self) -> tuple[float, int]:
        """(Σ NIS, Σ dof) over the window."""
        return float(sum(n for n, _ in self._items)), int(sum(d for _, d in self._items))

    def band(self) -> tuple[float, float]:
        """Acceptance region of Σ NIS for the window's Σ dof."""
        return chi2_band(self.totals()[1], self.alpha)

    def consistent(self) -> bool:
        """Full and Σ NIS inside the band."""
        return self.verdict() == "ok"

    def verdict(self) -> str:
        """One of "filling" (not full), "high" (Σ NIS above the band: the filter is overconfident or the model
        misses something), "low" (below: more cautious than it needs to be) or "ok"."""
        if not self.full:
            return "filling"
        lo, hi = self.band()
        total, _ = self.totals()
        return "high" if total > hi else "low" if total < lo else "ok"


def convergence(
    rom: Any,
    est: Estimate,
    window: NisWindow,
    *,
    sensor_std_bound_c: float = 0.1,
    field_rms_bound_c: float = 1.0,
) -> Convergence:
    """Converged when (1) every sensor's 1σ ≤ ``sensor_std_bound_c`` [°C], (2) the heat-capacity-weighted RMS
    of the field's 1σ, √(tr P / C_tot), ≤ ``field_rms_bound_c`` [°C] (the unobserved interior too) and (3) the
    NIS over a full window is not above its χ² band (``NisWindow``). A NIS below the band (the covariance is
    larger than the errors: the considered H errors of a hot spindle) is flagged ``nis_low`` only."""
    sens_std = float(field_std(np.asarray(rom.sensors), est.cov).max())
    u = uniform_state(rom)
    rms = float(np.sqrt(max(np.trace(est.cov), 0.0) / float(u @ u)))  # uᵀu = total heat capacity [J/K]
    total, dof = window.totals()
    band = window.band()
    reasons = []
    if sens_std > sensor_std_bound_c:
        reasons.append(f"sensor 1σ {sens_std:.3g} °C > {sensor_std_bound_c:g} °C")
    if rms > field_rms_bound_c:
        reasons.append(f"field RMS 1σ {rms:.3g} °C > {field_rms_bound_c:g} °C")
    verdict = window.verdict()
    if verdict == "filling":
        reasons.append(f"NIS window {window.count}/{window.size} samples")
    elif verdict == "high":
        reasons.append(f"NIS {total:.1f} above the χ²({dof}) band [{band[0]:.1f}, {band[1]:.1f}]")
    return Convergence(
        not reasons, "; ".join(reasons) or "converged", sens_std, rms, total, dof, band, verdict == "low"
    )


class StateEstimator:
    """The live state's Kalman filter on a ``ReducedModel`` (thin holder of the pure steps above).

    ``estimate`` is the current belief (e.g. ``wide_prior``); ``offsets_c`` (32,) [°C] are subtracted from
    every measurement before the update. Transitions are cached per (H, Δt) (the last ``cache_size``).
    """

    def __init__(
        self,
        rom: Any,
        estimate: Estimate,
        *,
        noise: NoiseModel | None = None,
        offsets_c: ArrayLike | None = None,
        cache_size: int = 8,
    ) -> None:
        self.rom = rom
        self.r = int(rom.k0.shape[0])
        self.noise = noise or NoiseModel()
        self._check_estimate(estimate)
        self.estimate = estimate
        self._sensors = np.ascontiguousarray(rom.sensors, dtype=np.float64)
        n_ch = self._sensors.shape[0]
        off = np.zeros(n_ch) if offsets_c is None else np.asarray(offsets_c, dtype=np.float64)
        if off.shape != (n_ch,) or not np.all(np.isfinite(off)):
            raise EstimatorError(f"offsets_c: expected {n_ch} finite values, got shape {off.shape}")
        self.offsets_c = off
        if self.noise.model_cov is not None and np.shape(self.noise.model_cov) != (self.r, self.r):
            raise EstimatorError(f"noise.model_cov: expected shape ({self.r}, {self.r})")
        self._cache: dict[tuple[bytes, float], Transition] = {}
        self._cache_size = int(cache_size)

    def _check_estimate(self, est: Estimate) -> None:
        r = self.r
        if est.mean.shape != (r,) or est.cov.shape != (r, r) or est.cross.shape != (r, N_PARAMS):
            raise EstimatorError(
                f"estimate: expected mean ({r},), cov ({r}, {r}) and cross ({r}, {N_PARAMS})"
            )
        if not all(np.all(np.isfinite(x)) for x in (est.mean, est.cov, est.cross)):
            raise EstimatorError("estimate: mean, cov and cross must be finite")

    def transition(self, h: ArrayLike, dt_s: float) -> Transition:
        """The (cached) step for H and Δt."""
        h_arr = np.asarray(h, dtype=np.float64)
        key = (h_arr.tobytes(), float(dt_s))
        tr = self._cache.get(key)
        if tr is None:
            tr = transition(self.rom, h_arr, dt_s)  # validates H and Δt
            if len(self._cache) >= self._cache_size:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = tr
        return tr

    def set_noise(self, noise: NoiseModel) -> None:
        """Use ``noise`` from now on. A change of the considered parameters' 1σ (``h_rel``, ``load_rel``)
        rescales their cross-covariance with the state (``rescale_cross``), so the joint covariance stays a
        covariance; the state's own P is unchanged."""
        if noise.model_cov is not None and np.shape(noise.model_cov) != (self.r, self.r):
            raise EstimatorError(f"noise.model_cov: expected shape ({self.r}, {self.r})")
        self.estimate = rescale_cross(self.estimate, self.noise.param_std(), noise.param_std())
        self.noise = noise

    def predict(self, inputs: StepInput) -> Estimate:
        """Advance the belief over one step (no measurement); ``CovarianceError`` (the belief left as it was)
        if the predicted covariance is not a covariance (``check_covariance``)."""
        self._check_inputs(inputs)
        tr = self.transition(inputs.h, inputs.dt_s)
        post = predict(self.rom, tr, self.estimate, inputs, self.noise)
        check_covariance(post)
        self.estimate = post
        return self.estimate

    def update(self, measured_c: ArrayLike, mask: ArrayLike | None = None) -> StepResult:
        """Correct the belief with one sample's channels (32,) [°C]; ``mask`` True = usable.
        ``CovarianceError`` (the belief left as it was) if the posterior is not a distribution
        (``check_covariance``)."""
        y = np.asarray(measured_c, dtype=np.float64)
        if y.shape != self.offsets_c.shape:
            raise EstimatorError(f"measurement: expected shape {self.offsets_c.shape}, got {y.shape}")
        y = y - self.offsets_c
        use = usable(y, mask)
        prior = self.estimate
        post, nu, nis, s_diag = update(self._sensors, prior, y, use, self.noise.r_var)
        check_covariance(post)
        innovation = np.full(y.shape, np.nan)
        innovation[use] = nu
        self.estimate = post
        return StepResult(post, innovation, nis, int(use.sum()), self._sensors @ prior.mean, np.sqrt(s_diag))

    def step(self, inputs: StepInput, measured_c: ArrayLike, mask: ArrayLike | None = None) -> StepResult:
        """Predict over the step, then update with the new sample: returns posterior, innovation and NIS."""
        self.predict(inputs)
        return self.update(measured_c, mask)

    def _check_inputs(self, u: StepInput) -> None:
        for name in ("ambient_c", "q_front_w", "q_rear_w", "dt_s"):
            if not np.isfinite(getattr(u, name)):
                raise EstimatorError(f"inputs.{name}: must be finite, got {getattr(u, name)!r}")

    def sensors_mean(self) -> Array:
        """Mean at the 32 sensors [°C] (model frame: add ``offsets_c`` to compare with raw readings)."""
        return np.asarray(self._sensors @ self.estimate.mean)

    def sensors_std(self) -> Array:
        """1σ at the 32 sensors [°C] from the state covariance (without measurement noise)."""
        return field_std(self._sensors, self.estimate.cov)

    def field_mean(self, nodes: ArrayLike | None = None) -> Array:
        """Mean field V·a [°C] at all nodes (N,) or at the node indices ``nodes``."""
        basis = self.rom.basis if nodes is None else self.rom.basis[np.asarray(nodes)]
        return np.asarray(basis @ self.estimate.mean)

    def field_std(self, nodes: ArrayLike | None = None) -> Array:
        """Field 1σ [°C] per node, √diag(V·P·Vᵀ) (all nodes or the indices ``nodes``); ~N·r² flops."""
        basis = self.rom.basis if nodes is None else self.rom.basis[np.asarray(nodes)]
        return field_std(basis, self.estimate.cov)

    def start_cov(self) -> Array:
        """The covariance (r, r) [°C²] to hand an identification window starting now (``start_cov``)."""
        return np.array(self.estimate.cov)

    def reset(self, estimate: Estimate) -> None:
        """Replace the belief (e.g. a new wide prior after a long gap)."""
        self._check_estimate(estimate)
        self.estimate = replace(estimate)
