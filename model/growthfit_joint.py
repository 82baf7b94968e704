"""The commissioning fit on several displacement series at once, with correlated residuals (pure).

``model.growthfit.fit_mechanics`` fits one series (the axial nose displacement) with white noise. A real
test fits against the **service's estimated field**, whose error is slow: the residuals are correlated in
time, and an axial series alone leaves the restraint s and the shaft's α factor a_s nearly interchangeable
(measured on a drawn plant, s 0.68 and a_s 0.96: the axial fit alone gave s 0.34 ± 0.02 and a_s 0.63 ±
0.02, far outside their CIs). Two changes, both standard:

- **joint series**: the radial nose displacement depends on a_s and barely on s (6.15 µm free and held at
  5000 rpm, docs/design/growth.md), so fitting it beside the axial one pins a_s and frees s. Each series has
  its own fixture offset and drift; the mechanical parameters are shared::

      y_i,k = (1 − s) G_i,free(a)·ΔT_k + s G_i,held(a)·ΔT_k + c_i + d_i (t_k − t_0)/3600 + e_i,k

- **correlated residuals**: each series' σ_i is its residual RMS inflated by √(n / n_eff), n_eff = n / (1 + 2
  Σ_k ρ_k) the effective number of independent readings, ρ_k the residuals' autocorrelation at lag k summed
  while positive (the initial positive sequence; by reading index, so irregular sampling counts as even).
  A lag-1 AR(1) factor is not enough: at 1 Hz the slow error's correlation spans hundreds of readings (a 4-h
  test at 1 Hz then claimed 370 independent readings, and α housing went to 1.43). Iterated (σ, n_eff from
  the fit before).
- **outliers**: a reading whose residual exceeds ``OUTLIER_K`` robust σ (1.4826 · MAD of its series) is left
  out of the next pass, and counted; a field estimate that jumps for a few minutes (the live state's, measured
  once on a drawn plant: 250 °C for a minute after a stop) would otherwise drag a_s to 0.

Parameters: ``restraint, alpha_shaft, alpha_housing`` then ``offset_um, drift_um_per_h`` per series
(suffixed by the series' name after the first). Priors as ``model.growthfit.MechanicsPrior``.

Errors::

    GrowthFitError(ValueError)   series of mismatched shapes, too few usable readings (from model.growthfit)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize_scalar

from model.growthfit import Z95, GrowthFitError, MechanicsFitResult, MechanicsPrior

Array = NDArray[np.float64]
PASSES = 4
OUTLIER_K = 6.0

__all__ = ["FitSeries", "JointFit", "correlation_factor", "fit_mechanics_joint"]


@dataclass(frozen=True)
class FitSeries:
    """One displacement series: ``name``, features (n, 2, 3) (``model.growthfit.features`` of its output),
    times (n,) [s] and readings (n,) [µm] (NaN: missing)."""

    name: str
    feats: ArrayLike
    times_s: ArrayLike
    displacement_um: ArrayLike


@dataclass(frozen=True)
class JointFit:
    """``result``: the fit (``x``, ``cov``, ``sd``, ``ci95`` over all parameters; residuals, RMS and max of
    the first series' readings kept); per series its residuals [µm] (kept readings), σ used [µm], the
    correlation factor n / n_eff (``rho``), readings left out as outliers and the kept readings' mask over its
    usable ones."""

    result: MechanicsFitResult
    residuals_um: tuple[Array, ...]
    sigma_um: tuple[float, ...]
    rho: tuple[float, ...]
    names: tuple[str, ...]
    outliers: tuple[int, ...] = ()
    kept: tuple[NDArray[np.bool_], ...] = ()


@dataclass(frozen=True)
class _S:
    f: Array
    tau_h: Array
    y: Array


def _prepare(series: Sequence[FitSeries]) -> list[_S]:
    if not series:
        raise GrowthFitError("series: need at least one displacement series")
    raw = []
    for s in series:
        f = np.asarray(s.feats, dtype=float)
        t = np.asarray(s.times_s, dtype=float)
        y = np.asarray(s.displacement_um, dtype=float)
        if f.ndim != 3 or f.shape[1:] != (2, 3) or t.shape != (f.shape[0],) or y.shape != t.shape:
            raise GrowthFitError(
                f"series {s.name!r}: expected feats (n, 2, 3), times (n,), displacement (n,); "
                f"got {f.shape}, {t.shape}, {y.shape}"
            )
        ok = np.isfinite(y) & np.isfinite(t) & np.all(np.isfinite(f), axis=(1, 2))
        if int(ok.sum()) < 10:
            raise GrowthFitError(f"series {s.name!r}: {int(ok.sum())} usable readings, need >= 10")
        raw.append((f[ok], t[ok], y[ok]))
    t0 = min(float(t[0]) for _, t, _ in raw)
    return [_S(f=f, tau_h=(t - t0) / 3600.0, y=y) for f, t, y in raw]


def _blend(f: Array, s: float) -> Array:
    return np.asarray(np.einsum("kmj,m->kj", f, np.array([1.0 - s, s])))


def _linear(data: list[_S], s: float, prior: MechanicsPrior, sig: Array) -> tuple[Array, float]:
    """(a_s, a_h, c_1, d_1, c_2, d_2, ...) at s and the objective."""
    m = len(data)
    rows, rhs_y = [], []
    for i, d in enumerate(data):
        bl = _blend(d.f, s)
        a = np.zeros((d.y.size, 2 + 2 * m))
        a[:, 0], a[:, 1] = bl[:, 1], bl[:, 2]
        a[:, 2 + 2 * i] = 1.0
        a[:, 3 + 2 * i] = d.tau_h
        rows.append(a / sig[i])
        rhs_y.append((d.y - bl[:, 0]) / sig[i])
    a_all, r_all = np.vstack(rows), np.concatenate(rhs_y)
    mu = np.zeros(2 + 2 * m)
    prec = np.zeros(2 + 2 * m)
    mu[:2] = prior.alpha_shaft[0], prior.alpha_housing[0]
    prec[:2] = prior.alpha_shaft[1] ** -2, prior.alpha_housing[1] ** -2
    theta = np.linalg.solve(a_all.T @ a_all + np.diag(prec), a_all.T @ r_all + prec * mu)
    res = r_all - a_all @ theta
    obj = float(res @ res + np.sum(prec * (theta - mu) ** 2))
    obj += ((s - prior.restraint[0]) / prior.restraint[1]) ** 2
    return theta, obj


def _search(data: list[_S], prior: MechanicsPrior, sig: Array) -> tuple[float, Array, float, int, bool]:
    grid = np.linspace(0.0, 1.0, 21)
    objs = [_linear(data, float(s), prior, sig)[1] for s in grid]
    i = int(np.argmin(objs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(
        lambda s: _linear(data, float(s), prior, sig)[1],
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-6},
    )
    s_best = float(res.x) if res.fun <= objs[i] else float(grid[i])
    theta, obj = _linear(data, s_best, prior, sig)
    return s_best, theta, obj, grid.size + int(res.nfev), bool(res.success)


def _model(d: _S, x: Array, i: int) -> Array:
    s, a_s, a_h = x[:3]
    g = d.f[:, :, 0] + a_s * d.f[:, :, 1] + a_h * d.f[:, :, 2]
    return np.asarray((1.0 - s) * g[:, 0] + s * g[:, 1] + x[3 + 2 * i] + x[4 + 2 * i] * d.tau_h)


def _jacobian(d: _S, x: Array, i: int, m: int) -> Array:
    s, a_s, a_h = x[:3]
    g = d.f[:, :, 0] + a_s * d.f[:, :, 1] + a_h * d.f[:, :, 2]
    w = np.array([1.0 - s, s])
    j = np.zeros((d.y.size, 3 + 2 * m))
    j[:, 0] = g[:, 1] - g[:, 0]
    j[:, 1] = d.f[:, :, 1] @ w
    j[:, 2] = d.f[:, :, 2] @ w
    j[:, 3 + 2 * i] = 1.0
    j[:, 4 + 2 * i] = d.tau_h
    return j


def correlation_factor(r: ArrayLike) -> float:
    """n / n_eff = 1 + 2 Σ ρ_k over the initial positive autocorrelations of ``r`` (>= 1)."""
    x = np.asarray(r, dtype=float)
    x = x - x.mean()
    n = x.size
    if n < 3 or float(x @ x) == 0.0:
        return 1.0
    size = 1 << (2 * n - 1).bit_length()
    spec = np.fft.rfft(x, size)
    acf = np.fft.irfft(spec * np.conj(spec), size)[:n]
    rho = acf[1:] / acf[0]
    stop = np.flatnonzero(rho <= 0.0)
    pos = rho[: int(stop[0]) if stop.size else rho.size]
    return float(max(1.0, 1.0 + 2.0 * float(pos.sum())))


def fit_mechanics_joint(
    series: Sequence[FitSeries],
    *,
    prior: MechanicsPrior | None = None,
    correlated: bool = True,
) -> JointFit:
    """Fit s, a_s, a_h and each series' offset and drift (module docstring); σ_i from the residuals."""
    pr = prior if prior is not None else MechanicsPrior()
    full = _prepare(series)
    m = len(full)
    keep = [np.ones(d.y.size, dtype=bool) for d in full]
    data = full
    sig = np.ones(m)
    rho = np.ones(m)
    nfev = 0
    for _ in range(PASSES):
        data = [_S(f=d.f[k], tau_h=d.tau_h[k], y=d.y[k]) for d, k in zip(full, keep, strict=True)]
        s, theta, obj, n, ok = _search(data, pr, sig)
        nfev += n
        x = np.r_[s, theta[:2], theta[2:]]
        for i, d in enumerate(data):
            r = d.y - _model(d, x, i)
            rms = max(float(np.sqrt(np.mean(r**2))), 1e-6)
            rho[i] = correlation_factor(r) if correlated else 1.0
            sig[i] = rms * float(np.sqrt(rho[i]))
            r_all = full[i].y - _model(full[i], x, i)
            robust = 1.4826 * float(np.median(np.abs(r_all - np.median(r_all))))
            new = np.abs(r_all - np.median(r_all)) <= OUTLIER_K * max(robust, 1e-6)
            keep[i] = new if int(new.sum()) >= 10 else keep[i]
    data = [_S(f=d.f[k], tau_h=d.tau_h[k], y=d.y[k]) for d, k in zip(full, keep, strict=True)]
    s, theta, obj, n, ok = _search(data, pr, sig)
    nfev += n
    x = np.r_[s, theta[:2], theta[2:]]
    resid = tuple(d.y - _model(d, x, i) for i, d in enumerate(data))
    jac = np.vstack([_jacobian(d, x, i, m) / sig[i] for i, d in enumerate(data)])
    prior_sd = np.r_[pr.restraint[1], pr.alpha_shaft[1], pr.alpha_housing[1], np.full(2 * m, np.inf)]
    info = jac.T @ jac + np.diag(prior_sd**-2.0)
    cov = np.asarray(np.linalg.inv(info), dtype=np.float64)
    sd = np.sqrt(np.diag(cov))
    names = ["restraint", "alpha_shaft", "alpha_housing"]
    for i, ser in enumerate(series):
        tail = "" if i == 0 else f"_{ser.name}"
        names += [f"offset_um{tail}", f"drift_um_per_h{tail}"]
    r0 = resid[0]
    result = MechanicsFitResult(
        x=x,
        cov=cov,
        sd=sd,
        ci95=np.column_stack([x - Z95 * sd, x + Z95 * sd]),
        prior_sd=prior_sd,
        residual_um=r0,
        residual_rms_um=float(np.sqrt(np.mean(r0**2))),
        residual_max_um=float(np.max(np.abs(r0))),
        noise_um=float(sig[0]),
        n_used=int(sum(d.y.size for d in data)),
        fun=obj,
        nfev=nfev,
        success=ok,
        message="joint profiled least squares over "
        + ", ".join(s.name for s in series)
        + (", σ inflated for the residuals' correlation" if correlated else ""),
        names=tuple(names),
    )
    return JointFit(
        result=result,
        residuals_um=resid,
        sigma_um=tuple(float(v) for v in sig),
        rho=tuple(float(v) for v in rho),
        names=tuple(s.name for s in series),
        outliers=tuple(int((~k).sum()) for k in keep),
        kept=tuple(keep),
    )
