"""Fit the mechanics a spindle's growth model is unsure of to a measured displacement series (pure core).

Issue 27 item 2's least squares, without its shell. An ISO 230-3 thermal test gives a displacement y_k [µm]
at times t_k [s] (a capacitive sensor on a test mandrel, axial); the thermal side gives the field history
T_k (N,) [°C] (the service's estimate, or a plant's truth in a test). Once the field is known the growth is
linear in each mechanical parameter, so the model of the test is::

    y_k = (1 − s) · G_free(a_s, a_h)·ΔT_k + s · G_held(a_s, a_h)·ΔT_k + c + d · (t_k − t_0) / 3600 + e_k
    G_m(a_s, a_h) = g_m,other + a_s · g_m,shaft + a_h · g_m,housing          (exact: B is linear in α)

- s in [0, 1]: the mount's radial restraint as the fraction of the way from free to held. A real flange is
  a spring (``model.plantmech``: k = K_HALF · s / (1 − s)); the blend of the two idealisations is what the
  fit can afford, and it matches the spring to ≤ 0.2 µm of the 10.8 µm between them (5000 rpm, nose);
- a_s, a_h: α factors of the shaft's and the housing's material (``model.mechprior.alpha_region_scales``);
- c [µm], d [µm/h]: the sensor fixture's offset and the test setup's slow linear drift (nuisances).

For a fixed s the model is linear in (a_s, a_h, c, d): a regularised linear least squares (Gaussian priors on
a_s, a_h; none on c, d). s is then a bounded 1-D search (a grid, then a bounded Brent refinement) of the
profiled objective; the posterior covariance of all five comes from the model's Jacobian at the optimum and
the priors (s's own prior included), with σ the noise given or the residual RMS.

Errors::

    GrowthFitError(ValueError)   arrays of mismatched shapes, too few usable samples, a bad prior
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize_scalar

from model.errors import ModelError
from model.fem import FEModel
from model.geometry import SpindleSpec
from model.mechprior import alpha_region_scales
from model.thermoelastic import MechanicsVariant, build_growth_model

Array = NDArray[np.float64]
PARAMS = ("restraint", "alpha_shaft", "alpha_housing", "offset_um", "drift_um_per_h")
Z95 = 1.959963984540054


class GrowthFitError(ModelError, ValueError):
    """Bad input to the mechanics fit; the message names the argument."""


# ---------------------------------------------------------------- the basis (FE, once)


@dataclass(frozen=True)
class MechanicsBasis:
    """One output's operators (2, 3, N) [µm/K]: mount (free, held) × (other materials, shaft's, housing's
    material), each at α factor 1, so G_m(a_s, a_h) = g[m, 0] + a_s g[m, 1] + a_h g[m, 2]."""

    output: str
    operators: Array

    def growth_um(
        self,
        fields_c: ArrayLike,
        t_ref_c: float | ArrayLike,
        *,
        restraint: float,
        alpha_shaft: float = 1.0,
        alpha_housing: float = 1.0,
    ) -> Array:
        """The blended model's growth [µm] of fields (n, N) or (N,) over ``t_ref_c`` (no nuisances)."""
        f = features(self, fields_c, t_ref_c)
        return _mech_model(f, np.array([restraint, alpha_shaft, alpha_housing]))


def mechanics_basis(spec: SpindleSpec, fe: FEModel, *, output: str = "nose_axial") -> MechanicsBasis:
    """The six operators of ``output`` on ``fe``'s mesh (six growth-model builds, ~0.3 s each at the
    default mesh)."""
    base = np.array(alpha_region_scales(spec, 0.0, 0.0))  # 1 on the other regions, 0 on shaft and housing
    shaft = np.array(alpha_region_scales(spec, 1.0, 0.0)) - base
    housing = np.array(alpha_region_scales(spec, 0.0, 1.0)) - base
    groups = tuple(tuple(float(v) for v in g) for g in (base, shaft, housing))
    ops = np.zeros((2, 3, fe.n_nodes))
    for m, fix in enumerate(("axial", "axial_radial")):
        for j, scales in enumerate(groups):
            gm = build_growth_model(spec, fe, variant=MechanicsVariant(fix=fix, region_alpha_scale=scales))
            ops[m, j] = gm.operator(output)
    return MechanicsBasis(output=output, operators=ops)


def features(basis: MechanicsBasis, fields_c: ArrayLike, t_ref_c: float | ArrayLike) -> Array:
    """F (n, 2, 3) [µm]: each operator applied to each field's rise over ``t_ref_c`` (the fit's input)."""
    t = np.atleast_2d(np.asarray(fields_c, dtype=float))
    if t.shape[1] != basis.operators.shape[2]:
        raise GrowthFitError(f"fields_c: expected {basis.operators.shape[2]} nodes, got shape {t.shape}")
    rise = t - np.asarray(t_ref_c, dtype=float)
    return np.asarray(np.einsum("kn,mjn->kmj", rise, basis.operators))


# ---------------------------------------------------------------- the fit (pure, small)


@dataclass(frozen=True)
class MechanicsPrior:
    """Gaussian priors (mean, sd) of s and the α factors; the nuisances c, d have none (flat)."""

    restraint: tuple[float, float] = (0.5, 0.5)
    alpha_shaft: tuple[float, float] = (1.0, 0.05)
    alpha_housing: tuple[float, float] = (1.0, 0.05)

    def __post_init__(self) -> None:
        for name in ("restraint", "alpha_shaft", "alpha_housing"):
            mean, sd = getattr(self, name)
            if not (np.isfinite(mean) and np.isfinite(sd) and sd > 0):
                raise GrowthFitError(f"prior.{name}: need a finite mean and sd > 0, got {(mean, sd)}")


@dataclass(frozen=True)
class MechanicsFitResult:
    """The fit, scipy-style: ``x`` (5,) in ``PARAMS`` order, ``cov`` (5, 5) its posterior covariance, ``sd``
    and ``ci95`` (5, 2); residuals [µm] of the used samples; σ [µm] used; ``prior_sd`` (5,) (inf: flat)."""

    x: Array
    cov: Array
    sd: Array
    ci95: Array
    prior_sd: Array
    residual_um: Array
    residual_rms_um: float
    residual_max_um: float
    noise_um: float
    n_used: int
    fun: float  # the minimised objective (data misfit / σ² + prior terms)
    nfev: int
    success: bool
    message: str
    names: tuple[str, ...] = field(default=PARAMS)

    def as_dict(self) -> dict[str, float]:
        """Name -> value."""
        return {n: float(v) for n, v in zip(self.names, self.x, strict=True)}


def _mech_model(f: Array, p: Array) -> Array:
    s, a_s, a_h = p
    g = f[:, :, 0] + a_s * f[:, :, 1] + a_h * f[:, :, 2]  # (n, 2)
    return np.asarray((1.0 - s) * g[:, 0] + s * g[:, 1])


def _design(f: Array, tau_h: Array, s: float) -> tuple[Array, Array]:
    """For a fixed s: y ≈ b + A (a_s, a_h, c, d)."""
    w = np.array([1.0 - s, s])
    blend = np.einsum("kmj,m->kj", f, w)  # (n, 3)
    a = np.column_stack([blend[:, 1], blend[:, 2], np.ones_like(tau_h), tau_h])
    return blend[:, 0], a


def _linear(
    f: Array, y: Array, tau_h: Array, s: float, prior: MechanicsPrior, sigma: float
) -> tuple[Array, float]:
    """The regularised linear fit at s: (a_s, a_h, c, d) and the objective (misfit/σ² + all prior terms)."""
    b, a = _design(f, tau_h, s)
    mu = np.array([prior.alpha_shaft[0], prior.alpha_housing[0], 0.0, 0.0])
    prec = np.array([prior.alpha_shaft[1] ** -2, prior.alpha_housing[1] ** -2, 0.0, 0.0])
    lhs = a.T @ a / sigma**2 + np.diag(prec)
    rhs = a.T @ (y - b) / sigma**2 + prec * mu
    theta = np.linalg.solve(lhs, rhs)
    r = y - b - a @ theta
    obj = r @ r / sigma**2 + np.sum(prec * (theta - mu) ** 2)
    obj += ((s - prior.restraint[0]) / prior.restraint[1]) ** 2
    return theta, float(obj)


def _fit_at_sigma(
    f: Array, y: Array, tau_h: Array, prior: MechanicsPrior, sigma: float
) -> tuple[float, Array, float, int, bool]:
    grid = np.linspace(0.0, 1.0, 21)
    objs = [_linear(f, y, tau_h, float(s), prior, sigma)[1] for s in grid]
    i = int(np.argmin(objs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(
        lambda s: _linear(f, y, tau_h, float(s), prior, sigma)[1],
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-6},
    )
    s_best = float(res.x) if res.fun <= objs[i] else float(grid[i])
    theta, obj = _linear(f, y, tau_h, s_best, prior, sigma)
    return s_best, theta, obj, grid.size + int(res.nfev), bool(res.success)


def fit_mechanics(
    feats: ArrayLike,
    times_s: ArrayLike,
    displacement_um: ArrayLike,
    *,
    prior: MechanicsPrior | None = None,
    noise_um: float | None = None,
) -> MechanicsFitResult:
    """Fit s, a_s, a_h, c, d (module docstring) to ``displacement_um`` (n,) [µm] at ``times_s`` (n,) [s],
    given ``feats`` (n, 2, 3) from ``features`` on the field history. NaN samples (displacement or field)
    are dropped. ``noise_um`` σ [µm] of the displacement sensor; None: the residual RMS (two passes)."""
    f = np.asarray(feats, dtype=float)
    t = np.asarray(times_s, dtype=float)
    y = np.asarray(displacement_um, dtype=float)
    if f.ndim != 3 or f.shape[1:] != (2, 3) or t.shape != (f.shape[0],) or y.shape != t.shape:
        raise GrowthFitError(
            f"displacement_um: expected feats (n, 2, 3), times (n,), displacement (n,); "
            f"got {f.shape}, {t.shape}, {y.shape}"
        )
    pr = prior if prior is not None else MechanicsPrior()
    ok = np.isfinite(y) & np.isfinite(t) & np.all(np.isfinite(f), axis=(1, 2))
    if int(ok.sum()) < 2 * len(PARAMS):
        raise GrowthFitError(f"displacement_um: {int(ok.sum())} usable samples, need >= {2 * len(PARAMS)}")
    if noise_um is not None and not noise_um > 0:
        raise GrowthFitError(f"noise_um: must be > 0, got {noise_um!r}")
    f, t, y = f[ok], t[ok], y[ok]
    tau_h = (t - t[0]) / 3600.0
    sigma = 1.0 if noise_um is None else float(noise_um)
    nfev = 0
    for _ in range(1 if noise_um is not None else 2):
        s, theta, obj, n, converged = _fit_at_sigma(f, y, tau_h, pr, sigma)
        nfev += n
        if noise_um is None:
            r = y - _full(f, tau_h, np.r_[s, theta])
            sigma = max(float(np.sqrt(r @ r / max(y.size - len(PARAMS), 1))), 1e-6)
    x = np.r_[s, theta]
    r = y - _full(f, tau_h, x)
    jac = _jacobian(f, tau_h, x)
    prior_sd = np.array([pr.restraint[1], pr.alpha_shaft[1], pr.alpha_housing[1], np.inf, np.inf])
    info = jac.T @ jac / sigma**2 + np.diag(prior_sd**-2.0)
    cov = np.asarray(np.linalg.inv(info), dtype=np.float64)
    sd = np.sqrt(np.diag(cov))
    return MechanicsFitResult(
        x=x,
        cov=cov,
        sd=sd,
        ci95=np.column_stack([x - Z95 * sd, x + Z95 * sd]),
        prior_sd=prior_sd,
        residual_um=r,
        residual_rms_um=float(np.sqrt(np.mean(r**2))),
        residual_max_um=float(np.max(np.abs(r))),
        noise_um=sigma,
        n_used=int(y.size),
        fun=obj,
        nfev=nfev,
        success=converged,
        message="profiled least squares: restraint by a bounded search, the rest linear"
        + ("" if converged else " (the bounded search did not converge)"),
    )


def _full(f: Array, tau_h: Array, x: Array) -> Array:
    return _mech_model(f, x[:3]) + x[3] + x[4] * tau_h


def _jacobian(f: Array, tau_h: Array, x: Array) -> Array:
    """∂ model / ∂ (s, a_s, a_h, c, d) (n, 5) at x (exact: the model is bilinear)."""
    s, a_s, a_h = x[:3]
    g = f[:, :, 0] + a_s * f[:, :, 1] + a_h * f[:, :, 2]
    w = np.array([1.0 - s, s])
    return np.column_stack([g[:, 1] - g[:, 0], f[:, :, 1] @ w, f[:, :, 2] @ w, np.ones_like(tau_h), tau_h])
