"""The thermal growth a compensation controller acts on, with its 95 % CI and forecast (pure, no I/O).

Three stages, by how often their inputs change (docs/design/growth.md, "Serving"):

1. ``build_context(spec, fe, basis=...)`` once per model: the growth operators g (``model.thermoelastic``)
   of the two served outputs, nose axial and nose radial growth [µm/K], and g·Φ for a reduced basis Φ.
2. ``condition_terms(ctx, h=..., cov_h=..., ambient_c=..., ...)`` once per (H, its covariance, condition):
   the steady field and its growth, ∂T_ss/∂H, the slowest thermal modes and, per horizon, the linear
   functional w_n that maps the current field to the growth n steps ahead (about 0.3 s at the default mesh).
3. ``estimate_growth(ctx, terms, belief, t_ref_c=..., at=...)`` per request: dot products only.

The forecast holds the condition and H. With the E-orthonormal slowest modes v_k (τ_k) of K(H) v = λ E v
and backward Euler at Δt (the service's discretisation, μ_k = 1/(1 + Δt/τ_k)), the growth n steps ahead is

    y(n) = y_ss + w_n·(T − T_ss),   w_n = Σ_k (g·v_k)(μ_k^n − μ_*^n) E v_k + μ_*^n g

where the part of g·(T − T_ss) outside the k modes decays like the fastest computed mode μ_* (its modes
are all faster). Its error against a full backward-Euler march is tested (``tests/estimate``).

Uncertainty, each part reported and combined as independent (σ² = σ_field² + σ_H² + σ_mech²):

- field part: the live state's belief (``FieldBelief``): a reduced covariance P (r, r) (the Kalman filter's,
  ``model.estimator``; a carried ensemble's, ``model.carry``), reduced ensemble deviations, a nodal factor
  U (Σ = UUᵀ), or per-node 1σ only (then bounded by full correlation: σ ≤ Σ|g_i|σ_i). Exact through the
  linear operators; at a horizon through w_n.
- H part: H's covariance Σ_H (``h_cov_from_ci``) through ∂T_ss/∂H (exact at steady state; at a horizon
  through (g − w_n), neglecting the change of the modes with H). For *now* it is counted only when the
  field's belief does not already contain H's error (``FieldBelief.includes_h``, true for the Kalman filter
  with considered H and for a carried ensemble, whose members ran with their own H); otherwise the steady
  Jacobian stands in for the current field's (exact at steady state, an over-estimate early in a warm-up).
- mechanical part (only with a commissioned calibration, ``with_mechanics``): the posterior of the mount
  restraint and the α factors (``service.estimate.mechanics``) through ∂g/∂θ·(T − T_ref); exact now and at
  steady state; at a horizon the larger of the two (the field between them is not formed). With probe
  readings absorbed, the fixture offset b they measured (``service.estimate.probe``) is added to every served
  axial growth, and Var(b) + 2 ∂g/∂θ·Cov(θ, b) joins the axial mechanical part.

Errors::

    GrowthEstimateError(ValueError)   a belief, covariance or input of the wrong shape or value (named)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.fem import FEModel, steady_state
from model.geometry import SpindleSpec
from model.growth import (
    Z95,
    reconstruction_h_fit,
    sensor_sensitivity,
    steady_jacobian_h,
    thermal_modes,
)
from model.thermoelastic import GrowthModel, build_growth_model
from service.contracts.growth import GrowthEstimate, GrowthForecastEstimate, GrowthValue, PlcCompensation
from service.errors import ServiceError

__all__ = [
    "ConditionTerms",
    "FieldBelief",
    "GrowthContext",
    "GrowthEstimateError",
    "build_context",
    "condition_terms",
    "estimate_growth",
    "h_cov_from_ci",
    "plc_compensation",
    "with_mechanics",
]

Array = NDArray[np.float64]
SERVED = ("nose_axial", "nose_radial")
HORIZONS_S = (300.0, 900.0, 1800.0)
N_H = 7


class GrowthEstimateError(ServiceError, ValueError):
    """Bad input to the growth estimate; the message names the field."""


# ---------------------------------------------------------------- once per model


@dataclass(frozen=True, eq=False, kw_only=True)
class GrowthContext:
    """The served outputs' operators: ``g`` (2, N) [µm/K] (nose axial, nose radial), ``g_phi`` (2, r) for
    the reduced basis ``phi`` (N, r) (None without a basis), and the full ``growth`` model."""

    fe: FEModel
    growth: GrowthModel
    g: Array
    phi: Array | None
    g_phi: Array | None
    # a commissioned calibration (``with_mechanics``): ∂g/∂θ (2, 3, N), its reduced (2, 3, r), Σ_θ (3, 3)
    g_mech: Array | None = None
    g_mech_phi: Array | None = None
    cov_mech: Array | None = None
    # the fixture offset the probe readings measured (``with_mechanics``): b [µm] added to the axial growth,
    # Var(b) [µm²], Cov(θ, b) (3,) [µm]
    offset_um: float = 0.0
    offset_var_um2: float = 0.0
    offset_cov_mech: Array | None = None


def with_mechanics(
    ctx: GrowthContext,
    operators: ArrayLike,
    jacobian: ArrayLike,
    cov: ArrayLike,
    *,
    offset: tuple[float, float, ArrayLike] | None = None,
) -> GrowthContext:
    """``ctx`` with the calibrated operators g(θ) (2, N), their Jacobian ∂g/∂θ (2, 3, N) and the posterior
    Σ_θ (3, 3) (``service.estimate.mechanics``); the growth model (section drawing) keeps its own.
    ``offset``: the fixture offset (b [µm], Var(b) [µm²], Cov(θ, b) (3,) [µm]; ``service.estimate.probe``),
    added to every served axial growth with its variance and its covariance with θ (None: none)."""
    g = np.asarray(operators, dtype=float)
    jac = np.asarray(jacobian, dtype=float)
    c = np.asarray(cov, dtype=float)
    n = ctx.fe.n_nodes
    if g.shape != (2, n) or jac.shape != (2, 3, n) or c.shape != (3, 3):
        raise GrowthEstimateError(
            f"mechanics: expected operators (2, {n}), jacobian (2, 3, {n}), cov (3, 3); "
            f"got {g.shape}, {jac.shape}, {c.shape}"
        )
    b, var_b, cov_b = (0.0, 0.0, None) if offset is None else offset
    cb = None if cov_b is None else np.asarray(cov_b, dtype=float)
    if not (np.isfinite(b) and np.isfinite(var_b) and var_b >= 0.0) or (
        cb is not None and (cb.shape != (3,) or not np.all(np.isfinite(cb)))
    ):
        raise GrowthEstimateError(f"offset: expected finite (b, Var(b) >= 0, Cov(θ, b) (3,)), got {offset!r}")
    return replace(
        ctx,
        g=g,
        g_phi=None if ctx.phi is None else g @ ctx.phi,
        g_mech=jac,
        g_mech_phi=None if ctx.phi is None else np.einsum("opn,nr->opr", jac, ctx.phi),
        cov_mech=0.5 * (c + c.T),
        offset_um=float(b),
        offset_var_um2=float(var_b),
        offset_cov_mech=cb,
    )


def build_context(
    spec: SpindleSpec, fe: FEModel, *, growth: GrowthModel | None = None, basis: ArrayLike | None = None
) -> GrowthContext:
    """Build (or take) the growth model on ``fe``'s mesh; ``basis`` Φ (N, r): the reduced model's, if any."""
    gm = growth if growth is not None else build_growth_model(spec, fe)
    if gm.n_nodes != fe.n_nodes:
        raise GrowthEstimateError(f"growth: built on {gm.n_nodes} nodes, the FE model has {fe.n_nodes}")
    missing = [n for n in SERVED if n not in gm.names]
    if missing:
        raise GrowthEstimateError(f"growth: outputs {missing} missing ([[mechanics.outputs]] in the TOML)")
    g = np.array([gm.operator(n) for n in SERVED])
    phi = None if basis is None else np.asarray(basis, dtype=float)
    if phi is not None and (phi.ndim != 2 or phi.shape[0] != fe.n_nodes):
        raise GrowthEstimateError(f"basis: expected shape ({fe.n_nodes}, r), got {phi.shape}")
    return GrowthContext(fe=fe, growth=gm, g=g, phi=phi, g_phi=None if phi is None else g @ phi)


# ---------------------------------------------------------------- H covariance


def h_cov_from_ci(h: ArrayLike, ci95: ArrayLike, correlation: ArrayLike | None = None) -> Array:
    """Σ_H (7, 7) [(W/(m²·K))²] from an identification's log-H 95 % CI (``IdentificationResult.h_ci95``,
    lo = H·e^(−zσ), hi = H·e^(zσ)) and its correlation (None: uncorrelated), linearised: Σ_H = D Σ_log D,
    D = diag(H). An unbounded CI (not identified) gives an unbounded variance: the growth says so."""
    hv, ci = np.asarray(h, dtype=float), np.asarray(ci95, dtype=float)
    if hv.shape != (N_H,) or not np.all(hv > 0):
        raise GrowthEstimateError(f"h: expected {N_H} values > 0, got {hv!r}")
    if (
        ci.shape != (N_H, 2)
        or not np.all(np.isfinite(ci))
        or np.any(ci[:, 0] <= 0)
        or np.any(ci[:, 1] < ci[:, 0])
    ):
        raise GrowthEstimateError(f"ci95: expected ({N_H}, 2) finite with 0 < low <= high, got {ci!r}")
    sigma_log = 0.5 * np.log(ci[:, 1] / ci[:, 0]) / Z95
    corr = np.eye(N_H) if correlation is None else np.asarray(correlation, dtype=float)
    if corr.shape != (N_H, N_H):
        raise GrowthEstimateError(f"correlation: expected ({N_H}, {N_H}), got {corr.shape}")
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    s = hv * sigma_log
    return np.asarray(s[:, None] * corr * s[None, :])


# ---------------------------------------------------------------- once per condition


@dataclass(frozen=True, eq=False, kw_only=True)
class ConditionTerms:
    """Everything that depends on H, Σ_H and the held condition (see the module docstring).

    ``steady_um`` (2,) growth of the steady field T_ss over a zero reference (add −g·T_ref); ``jg`` (2, 7)
    [µm per W/(m²·K)] = g·∂T_ss/∂H; ``horizons_s`` (n_h,); ``w`` (n_h, 2, N) the horizon functionals,
    ``w_phi`` (n_h, 2, r); ``w_ss`` (n_h, 2) = w·T_ss; ``jw`` (n_h, 2, 7) = (g − w)·∂T_ss/∂H; ``modes_e``
    (N, k) = E·V (``modes_e_phi`` (k, r) = VᵀEΦ, ``modes_ss`` (k,) = VᵀE·T_ss) and ``modes_g`` (2, k) = g·V
    for the dominant time constant; ``tau_s`` (k,);
    ``sens`` (2, 32) [µm/°C] growth per unit sensor error.

    ``compact()`` drops the nodal ``w`` and ``modes_e`` (None): what a reduced belief (the service's live
    state) does not use, 1.2 of the 1.27 MiB of one condition's terms on the service mesh (issue 43 part 5).
    """

    h: Array
    cov_h: Array
    ambient_c: float
    q_front_w: float
    q_rear_w: float
    load_scale: tuple[float, float]
    t_ss: Array
    steady_um: Array
    jg: Array
    horizons_s: Array
    w: Array | None  # None: compact (``compact()``)
    w_phi: Array | None
    w_ss: Array
    jw: Array
    modes_e: Array | None  # None: compact
    modes_e_phi: Array | None
    modes_ss: Array
    modes_g: Array
    tau_s: Array
    sens: Array

    def compact(self) -> ConditionTerms:
        """These terms without the nodal functionals (``w``, ``modes_e``): for reduced beliefs only (an
        estimate from a nodal one then raises ``GrowthEstimateError``); the same terms when there is no
        reduced basis to use instead."""
        if self.w_phi is None or self.modes_e_phi is None:
            return self
        return replace(self, w=None, modes_e=None)


def _horizon_functionals(
    ctx: GrowthContext, vectors: Array, tau_s: Array, steps: NDArray[np.int64], dt_s: float
) -> Array:
    """w_n (n_h, 2, N) for backward Euler: the kept modes decay with their own μ, the rest like the last."""
    mu = 1.0 / (1.0 + dt_s / tau_s)  # (k+1,)
    ev = np.asarray(ctx.fe.E @ vectors)  # (N, k+1)
    gv = ctx.g @ vectors  # (2, k+1)
    out = np.empty((steps.size, 2, ctx.g.shape[1]))
    for i, n in enumerate(steps):
        rest = mu[-1] ** n
        coef = gv[:, :-1] * (mu[:-1] ** n - rest)[None, :]  # (2, k)
        out[i] = coef @ ev[:, :-1].T + rest * ctx.g
    return out


RITZ_BASIS_FACTOR = 4  # thermal modes from the reduced basis when it has >= 4x as many vectors as modes


def condition_terms(
    ctx: GrowthContext,
    *,
    h: ArrayLike,
    cov_h: ArrayLike,
    ambient_c: float,
    q_front_w: float,
    q_rear_w: float,
    load_scale: tuple[float, float] = (1.0, 1.0),
    horizons_s: Sequence[float] = HORIZONS_S,
    dt_s: float = 10.0,
    n_modes: int = 12,
    sensor_noise_c: float = 0.15,
    sensor_prior_rel: float = 0.3,
) -> ConditionTerms:
    """The per-condition terms for H (7,) [W/(m²·K)] with covariance ``cov_h`` (7, 7), the ambient [°C] and
    bearing heats [W] held; forecast horizons [s] (multiples of ``dt_s``); ``n_modes`` kept thermal modes.

    ``sens``: growth per unit sensor error [µm/°C] of an H fit linearised at the steady state, maximum a
    posteriori with σ = ``sensor_noise_c`` and a prior of ``sensor_prior_rel`` (1σ, relative) on each H
    (``model.growth.reconstruction_h_fit``): what one channel's offset does to the growth.
    """
    hv = np.asarray(h, dtype=float)
    ch = np.asarray(cov_h, dtype=float)
    if hv.shape != (N_H,) or not np.all(np.isfinite(hv)) or np.any(hv <= 0):
        raise GrowthEstimateError(f"h: expected {N_H} finite values > 0, got {hv!r}")
    if ch.shape != (N_H, N_H) or np.any(np.isnan(ch)):
        raise GrowthEstimateError(f"cov_h: expected a ({N_H}, {N_H}) covariance, got shape {ch.shape}")
    for name, v in (("ambient_c", ambient_c), ("q_front_w", q_front_w), ("q_rear_w", q_rear_w)):
        if not np.isfinite(v):
            raise GrowthEstimateError(f"{name}: must be finite, got {v!r}")
    hz = np.asarray(horizons_s, dtype=float)
    steps = np.rint(hz / dt_s).astype(np.int64)
    if hz.ndim != 1 or np.any(steps < 1) or np.any(np.abs(steps * dt_s - hz) > 1e-9 * np.maximum(hz, 1)):
        raise GrowthEstimateError(f"horizons_s: must be positive multiples of dt_s = {dt_s}, got {list(hz)}")
    cond = {"ambient_c": ambient_c, "q_front_w": q_front_w, "q_rear_w": q_rear_w, "load_scale": load_scale}
    t_ss = steady_state(ctx.fe, hv, **cond)  # type: ignore[arg-type]
    jac = steady_jacobian_h(ctx.fe, hv, t_ss=t_ss, **cond)  # type: ignore[arg-type]
    # Rayleigh–Ritz in the reduced basis when it is rich enough (the service's: r = 56 for 13 modes), else
    # Lanczos on the full model (docs/design/threading.md, "Growth refresh")
    rich = ctx.phi is not None and ctx.phi.shape[1] >= RITZ_BASIS_FACTOR * (n_modes + 1)
    modes = thermal_modes(ctx.fe, hv, n_modes=n_modes + 1, basis=ctx.phi if rich else None)
    w = _horizon_functionals(ctx, modes.vectors, modes.tau_s, steps, dt_s)
    jg = ctx.g @ jac
    modes_e = np.asarray(ctx.fe.E @ modes.vectors[:, :-1])
    recon = reconstruction_h_fit(
        ctx.fe, jac, noise_c=sensor_noise_c, prior_cov_h=np.diag((sensor_prior_rel * hv) ** 2)
    )
    return ConditionTerms(
        h=hv,
        cov_h=0.5 * (ch + ch.T),
        ambient_c=float(ambient_c),
        q_front_w=float(q_front_w),
        q_rear_w=float(q_rear_w),
        load_scale=(float(load_scale[0]), float(load_scale[1])),
        t_ss=t_ss,
        steady_um=ctx.g @ t_ss,
        jg=jg,
        horizons_s=np.asarray(steps * dt_s, dtype=float),
        w=w,
        w_phi=None if ctx.phi is None else np.einsum("hon,nr->hor", w, ctx.phi),
        w_ss=np.einsum("hon,n->ho", w, t_ss),
        jw=jg[None, :, :] - np.einsum("hon,nk->hok", w, jac),
        modes_e=modes_e,
        modes_e_phi=None if ctx.phi is None else modes_e.T @ ctx.phi,
        modes_ss=modes_e.T @ t_ss,
        modes_g=ctx.g @ modes.vectors[:, :-1],
        tau_s=np.asarray(modes.tau_s[:-1]),
        sens=sensor_sensitivity(ctx.g, recon),
    )


# ---------------------------------------------------------------- the live state's belief


@dataclass(frozen=True, eq=False, kw_only=True)
class FieldBelief:
    """The live field [°C] and its uncertainty, as the live state can give them.

    Mean: ``mean_c`` (N,) nodal or ``state`` (r,) reduced (field = Φ·a), exactly one. Uncertainty, at most
    one (none: the field part is 0): ``cov`` (r, r) reduced [°C²]; ``deviations`` (M, r) reduced ensemble
    deviations (second moment); ``factor`` (N, k) nodal, Σ = U·Uᵀ; ``std_c`` (N,) per-node 1σ only.
    ``includes_h``: the uncertainty already holds H's error (a filter with considered H, a carried ensemble).
    """

    mean_c: Array | None = None
    state: Array | None = None
    cov: Array | None = None
    deviations: Array | None = None
    factor: Array | None = None
    std_c: Array | None = None
    includes_h: bool = True


def _reduced_ops(ctx: GrowthContext, name: str) -> Array:
    if ctx.g_phi is None:
        raise GrowthEstimateError(f"belief.{name}: reduced, but the context has no basis (build_context)")
    return ctx.g_phi


def _mean_growth(ctx: GrowthContext, b: FieldBelief) -> tuple[Array, Array]:
    """The mean as given (nodal (N,) or reduced (r,)) and its g·T (2,) [µm over 0 °C]."""
    if (b.mean_c is None) == (b.state is None):
        raise GrowthEstimateError("belief: give exactly one of mean_c (N,) or state (r,)")
    if b.mean_c is not None:
        t = np.asarray(b.mean_c, dtype=float)
        if t.shape != (ctx.g.shape[1],) or not np.all(np.isfinite(t)):
            raise GrowthEstimateError(f"belief.mean_c: expected ({ctx.g.shape[1]},) finite, got {t.shape}")
        return t, ctx.g @ t
    a = np.asarray(b.state, dtype=float)
    gp = _reduced_ops(ctx, "state")
    if a.shape != (gp.shape[1],) or not np.all(np.isfinite(a)):
        raise GrowthEstimateError(f"belief.state: expected ({gp.shape[1]},) finite, got {a.shape}")
    return a, gp @ a


def _field_std(nodal: Array | None, reduced: Array | None, b: FieldBelief) -> Array:
    """1σ [µm] of rows of a nodal functional (m, N) (reduced (m, r)) under the belief's uncertainty; the
    nodal one may be None (compact terms) when the belief is reduced."""
    given = [x for x in (b.cov, b.deviations, b.factor, b.std_c) if x is not None]
    if len(given) > 1:
        raise GrowthEstimateError("belief: give at most one of cov, deviations, factor, std_c")
    if not given:
        return np.zeros(_nodal(nodal if reduced is None else reduced).shape[0])
    if b.factor is not None:
        nodal = _nodal(nodal)
        u = np.asarray(b.factor, dtype=float)
        if u.ndim != 2 or u.shape[0] != nodal.shape[1]:
            raise GrowthEstimateError(f"belief.factor: expected ({nodal.shape[1]}, k), got {u.shape}")
        return np.asarray(np.sqrt(np.sum((nodal @ u) ** 2, axis=1)))
    if b.std_c is not None:
        nodal = _nodal(nodal)
        s = np.asarray(b.std_c, dtype=float)
        if s.shape != (nodal.shape[1],):
            raise GrowthEstimateError(f"belief.std_c: expected ({nodal.shape[1]},), got {s.shape}")
        return np.asarray(np.abs(nodal) @ s)
    if reduced is None:
        raise GrowthEstimateError("belief: a reduced covariance needs a basis in the context")
    r = reduced.shape[1]
    if b.cov is not None:
        p = np.asarray(b.cov, dtype=float)
        if p.shape != (r, r):
            raise GrowthEstimateError(f"belief.cov: expected ({r}, {r}), got {p.shape}")
        var = np.einsum("ij,jk,ik->i", reduced, p, reduced)
        return np.asarray(np.sqrt(np.maximum(var, 0.0)))
    d = np.asarray(b.deviations, dtype=float)
    if d.ndim != 2 or d.shape[1] != r:
        raise GrowthEstimateError(f"belief.deviations: expected (M, {r}), got {d.shape}")
    return np.asarray(np.sqrt(np.mean((d @ reduced.T) ** 2, axis=0)))


# ---------------------------------------------------------------- the served estimate


def _h_std(rows: Array, cov_h: Array) -> Array:
    var = np.einsum("ij,jk,ik->i", rows, cov_h, rows)
    return np.asarray(np.sqrt(np.maximum(var, 0.0)))


def estimate_growth(
    ctx: GrowthContext,
    terms: ConditionTerms,
    belief: FieldBelief,
    *,
    t_ref_c: float,
    at: datetime,
    t_ref_sd_c: float = 0.0,
) -> GrowthEstimate:
    """The served growth for the live ``belief`` under ``terms`` (dot products only; see module docstring).

    ``t_ref_sd_c`` [°C]: the 1σ of the reference temperature (``service.estimate.reference``); its growth
    |g·1|·σ joins the field's part of every served 1σ (now, the horizons and the steady forecast), because
    every served growth is relative to it."""
    if at.tzinfo is None:
        raise GrowthEstimateError("at: must be timezone-aware (UTC)")
    if not np.isfinite(t_ref_c):
        raise GrowthEstimateError(f"t_ref_c: must be finite, got {t_ref_c!r}")
    if not (np.isfinite(t_ref_sd_c) and t_ref_sd_c >= 0.0):
        raise GrowthEstimateError(f"t_ref_sd_c: must be a finite 1σ >= 0 °C, got {t_ref_sd_c!r}")
    if terms.t_ss.shape[-1] != ctx.g.shape[1]:
        raise GrowthEstimateError(
            "terms: built for another mesh than the context (condition_terms(ctx, ...))"
        )
    x, gx = _mean_growth(ctx, belief)
    reduced_mean = belief.state is not None
    g1 = ctx.g.sum(axis=1)  # growth per uniform kelvin (2,)
    b = np.array([ctx.offset_um, 0.0])  # the fixture offset moves the tool axially only
    now = gx - g1 * t_ref_c + b
    ref_std = np.abs(g1) * float(t_ref_sd_c)  # the reference's part (2,) [µm]
    std_now = np.hypot(_field_std(ctx.g, ctx.g_phi, belief), ref_std)
    h_now = np.zeros(2) if belief.includes_h else _h_std(terms.jg, terms.cov_h)
    steady = terms.steady_um - g1 * t_ref_c + b
    h_ss = _h_std(terms.jg, terms.cov_h)
    m_now, m_ss = _mech_std(ctx, x, reduced_mean, terms.t_ss, t_ref_c)
    m_hz = np.maximum(m_now, m_ss)
    axial, radial = [], []
    for i in range(terms.horizons_s.size):
        w_i = None if terms.w is None else terms.w[i]
        wx = (terms.w_phi[i] if reduced_mean and terms.w_phi is not None else _nodal(w_i)) @ x
        y = steady + wx - terms.w_ss[i]
        s_f = np.hypot(_field_std(w_i, None if terms.w_phi is None else terms.w_phi[i], belief), ref_std)
        s_h = _h_std(terms.jw[i], terms.cov_h)
        axial.append(GrowthValue.of(y[0], s_f[0], s_h[0], m_hz[0]))
        radial.append(GrowthValue.of(y[1], s_f[1], s_h[1], m_hz[1]))
    modes_e = terms.modes_e_phi if reduced_mean and terms.modes_e_phi is not None else None
    proj = modes_e @ x if modes_e is not None else _nodal(terms.modes_e).T @ x
    gap = terms.modes_g[0] * (proj - terms.modes_ss)
    forecast = GrowthForecastEstimate(
        steady_axial=GrowthValue.of(steady[0], ref_std[0], h_ss[0], m_ss[0]),
        steady_radial=GrowthValue.of(steady[1], ref_std[1], h_ss[1], m_ss[1]),
        tau_s=float(terms.tau_s[int(np.argmax(np.abs(gap)))]),
        slowest_tau_s=float(terms.tau_s[0]),
        horizons_s=tuple(float(v) for v in terms.horizons_s),
        axial=tuple(axial),
        radial=tuple(radial),
    )
    return GrowthEstimate(
        at=at.astimezone(UTC),
        t_ref_c=float(t_ref_c),
        axial=GrowthValue.of(now[0], std_now[0], h_now[0], m_now[0]),
        radial=GrowthValue.of(now[1], std_now[1], h_now[1], m_now[1]),
        forecast=forecast,
        sensitivity_axial_um_per_k=tuple(float(v) for v in terms.sens[0]),
        sensitivity_radial_um_per_k=tuple(float(v) for v in terms.sens[1]),
        h=tuple(float(v) for v in terms.h),
        ambient_c=terms.ambient_c,
    )


def _nodal(arr: Array | None) -> Array:
    """A nodal functional of the terms (checked present: compact terms serve reduced beliefs only)."""
    if arr is None:
        raise GrowthEstimateError("terms: compact (no nodal functionals) for a nodal belief")
    return arr


def _mech_std(
    ctx: GrowthContext, x: Array, reduced_mean: bool, t_ss: Array, t_ref_c: float
) -> tuple[Array, Array]:
    """The mechanical 1σ (2,) [µm] now (field ``x``, nodal or reduced) and at the steady field ``t_ss``, over
    the uniform ``t_ref_c``, the fixture offset's part in the axial one (Var(b) + 2 j·Cov(θ, b)); zeros
    without a calibration in ``ctx``."""
    if ctx.g_mech is None or ctx.cov_mech is None:
        return np.zeros(2), np.zeros(2)
    ones = ctx.g_mech.sum(axis=2) * t_ref_c  # (2, 3)
    if reduced_mean and ctx.g_mech_phi is not None:
        j_now = ctx.g_mech_phi @ x - ones
    else:
        j_now = ctx.g_mech @ x - ones
    j_ss = ctx.g_mech @ t_ss - ones
    cov = np.asarray(ctx.cov_mech, dtype=np.float64)
    cb = np.zeros(3) if ctx.offset_cov_mech is None else ctx.offset_cov_mech

    def std(j: Array) -> Array:
        var = np.sum((j @ cov) * j, axis=1)
        var[0] += ctx.offset_var_um2 + 2.0 * float(j[0] @ cb)
        return np.asarray(np.sqrt(np.maximum(var, 0.0)))

    return std(j_now), std(j_ss)


# ---------------------------------------------------------------- controller values


def plc_compensation(growth_um: float, *, tool_dir: int = -1) -> PlcCompensation:
    """Map an axial nose growth [µm] (+ towards the tool) to controller values.

    ``tool_dir``: the direction the tool points along the machine axis, −1 when it points to −Z (ISO 841:
    +Z points away from the workpiece, so a vertical or a horizontal spindle's tool points to −Z), +1
    otherwise. Sign conventions differ between machine set-ups: check the sign once against a measured
    growth at commissioning.
    """
    if tool_dir not in (-1, 1):
        raise GrowthEstimateError(f"tool_dir: must be -1 or +1, got {tool_dir!r}")
    if not np.isfinite(growth_um):
        raise GrowthEstimateError(f"growth_um: must be finite, got {growth_um!r}")
    corr = -float(tool_dir) * float(growth_um)
    return PlcCompensation(
        growth_um=float(growth_um),
        correction_um=corr,
        sd43900_mm=corr * 1e-3,
        sd43910_slope=0.0,
        sd43920_ref_mm=0.0,
        sd42960_tool_axis_mm=float(growth_um) * 1e-3,
        isg_offset_0p1um=int(np.rint(10.0 * corr)),
        isg_coefficient_um_per_m=0.0,
        isg_position_0p1um=0,
    )
