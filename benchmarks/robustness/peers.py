"""The regression peers of the robustness bench, given their best shot (issue 40 part 2).

Each peer is fitted on the seed's ISO 230-3 thermal test only (the displacement readings against the
temperature rows at or before them) and predicts the axial displacement [µm] from the 32 temperatures and the
ambient [°C]:

- ``mlr``: the present MLR (``benchmarks.studies.mlr``: 5 sensors by correlation clustering, least squares);
- ``ridge``: all 32 channels + the ambient, standardised, an L2 penalty chosen by blocked cross-validation
  over time (Hoerl & Kennard 1970; for thermal errors e.g. Liu et al., Precision Engineering 2015);
- ``lasso``: the same with an L1 penalty (Tibshirani 1996), coordinate descent (Friedman et al. 2010),
  the penalty by the same blocked cross-validation;
- ``arx``: a dynamic regression with lagged temperatures (distributed lag / ARX without the output's own
  lags, which a controller does not measure online): every channel and the ambient at lags 0, Δ, …, LΔ
  (Δ = 10 min), ridge-penalised; the lag order L and the penalty both by blocked cross-validation
  (Ljung, System Identification, 1999, ch. 4; thermal errors: Horejš et al., 2016).

Blocked cross-validation: the test's rows in ``folds`` contiguous blocks in time, each held out once (rows
next to each other in time are not independent, so a random split would reward overfitting). The score is
the mean squared error over the held-out rows; the smallest wins.

Pure numpy (no scikit-learn: not a dependency).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = [
    "ARX_LAGS",
    "LinearPeer",
    "blocked_folds",
    "fit_arx",
    "fit_lasso",
    "fit_ridge",
    "hold_flagged",
    "lagged",
    "lasso_path",
    "ridge_solve",
]

ARX_LAGS = (0, 1, 2, 3, 4, 6)  # lag orders tried (each Δ = ``lag_rows`` rows)
RIDGE_GRID = tuple(float(x) for x in np.logspace(-6, 3, 28))  # λ relative to the row count
LASSO_GRID_N = 25  # λ from λ_max down to 1e-3 λ_max


class PeerError(ValueError):
    """Bad input to a peer's fit (shapes, too few rows); the message names the field."""


def blocked_folds(n: int, folds: int = 5) -> list[NDArray[np.int64]]:
    """Row indices of ``folds`` contiguous blocks covering 0..n-1 in order."""
    if folds < 2 or n < 2 * folds:
        raise PeerError(f"folds: need 2 <= folds and >= 2 rows per fold, got {folds} folds for {n} rows")
    return [np.asarray(b, dtype=np.int64) for b in np.array_split(np.arange(n), folds)]


def lagged(x: ArrayLike, rows: ArrayLike, lags: int, lag_rows: int) -> Array:
    """The design of ``rows`` of the series ``x`` (samples × channels): the row and the rows ``lag_rows``,
    2·``lag_rows``, … ``lags``·``lag_rows`` before it side by side (before the first sample: the first, the
    machine's state before the record started)."""
    xs = np.asarray(x, dtype=float)
    r = np.asarray(rows, dtype=np.int64)
    return np.hstack([xs[np.clip(r - lag * lag_rows, 0, None)] for lag in range(lags + 1)])


def _standardise(x: Array) -> tuple[Array, Array]:
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    return mean, np.where(scale > 1e-12, scale, np.inf)  # a constant column gets weight 0


def ridge_solve(z: Array, y: Array, lam: float) -> Array:
    """argmin ||y − z b||² / n + λ ||b||² (z, y centred) through the SVD."""
    u, s, vt = np.linalg.svd(z, full_matrices=False)
    n = z.shape[0]
    d = s / (s**2 + lam * n)
    return np.asarray(vt.T @ (d * (u.T @ y)))


def _soft(x: float, t: float) -> float:
    return float(np.sign(x) * max(abs(x) - t, 0.0))


def lasso_path(
    z: Array, y: Array, lams: Sequence[float] | Array, *, tol: float = 1e-5, max_iter: int = 400
) -> Array:
    """Coefficients (len(lams), p) of argmin ||y − z b||² / (2n) + λ ||b||₁ (z, y centred) along the
    decreasing ``lams``, coordinate descent with warm starts on the Gram matrix (Friedman, Hastie &
    Tibshirani 2010, "covariance updates"); a sweep ends the λ when no coefficient moved more than ``tol``."""
    n, p = z.shape
    gram = z.T @ z / n
    cov = z.T @ y / n
    col = np.diag(gram).copy()
    b = np.zeros(p)
    out = np.zeros((len(lams), p))
    for i, lam in enumerate(lams):
        for _ in range(max_iter):
            delta = 0.0
            for j in range(p):
                if col[j] <= 0.0:
                    continue
                old = b[j]
                rho = cov[j] - float(gram[j] @ b) + col[j] * old
                new = _soft(rho, lam) / col[j]
                if new != old:
                    b[j] = new
                    delta = max(delta, abs(new - old) * np.sqrt(col[j]))
            if delta < tol:
                break
        out[i] = b
    return out


@dataclass(frozen=True)
class LinearPeer:
    """A fitted linear peer: y ≈ intercept + Σ coef · (design − mean) / scale over the ``lags`` lagged
    copies of the features (``lag_rows`` rows apart), ``alpha`` the penalty chosen, ``cv_mse`` its blocked
    cross-validation score [µm²] (the grid's scores in ``cv_curve``)."""

    name: str
    lags: int
    lag_rows: int
    mean: Array
    scale: Array
    coef: Array
    intercept: float
    alpha: float
    cv_mse: float
    cv_curve: tuple[float, ...] = ()

    def predict_rows(self, x: ArrayLike, rows: ArrayLike) -> Array:
        """The displacement [µm] at ``rows`` of the feature series ``x`` (samples × features)."""
        d = lagged(x, rows, self.lags, self.lag_rows)
        if d.shape[1] != self.coef.size:
            n_in = d.shape[1] // (self.lags + 1)
            raise PeerError(f"x: expected {self.coef.size // (self.lags + 1)} features, got {n_in}")
        return np.asarray(((d - self.mean) / self.scale) @ self.coef + self.intercept)

    @property
    def active(self) -> int:
        """Non-zero coefficients."""
        return int(np.count_nonzero(np.abs(self.coef) > 1e-12))


def _prepare(x: ArrayLike, y: ArrayLike, rows: ArrayLike) -> tuple[Array, Array, NDArray[np.int64]]:
    xs, ys = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    r = np.asarray(rows, dtype=np.int64)
    if xs.ndim != 2 or ys.ndim != 1 or r.shape != ys.shape:
        raise PeerError(
            f"x (samples × features), y and rows (readings) disagree: {xs.shape}, {ys.shape}, {r.shape}"
        )
    ok = np.isfinite(ys) & np.isfinite(xs[r]).all(axis=1)
    if ok.sum() < 20:
        raise PeerError(f"y: too few finite readings ({int(ok.sum())})")
    return xs, ys[ok], r[ok]


def _cv_ridge(d: Array, y: Array, grid: Sequence[float], folds: int) -> Array:
    """Blocked-CV mean squared error per λ of ``grid``."""
    sse = np.zeros(len(grid))
    for test in blocked_folds(y.size, folds):
        train = np.setdiff1d(np.arange(y.size), test)
        mean, scale = _standardise(d[train])
        zt = (d[train] - mean) / scale
        zv = (d[test] - mean) / scale
        ym = y[train].mean()
        u, s, vt = np.linalg.svd(zt, full_matrices=False)
        uy = u.T @ (y[train] - ym)
        for i, lam in enumerate(grid):
            b = vt.T @ (s / (s**2 + lam * train.size) * uy)
            sse[i] += float(((y[test] - ym - zv @ b) ** 2).sum())
    return sse / y.size


def _fit_ridge_design(
    name: str, d: Array, y: Array, lags: int, lag_rows: int, grid: Sequence[float], folds: int
) -> LinearPeer:
    cv = _cv_ridge(d, y, grid, folds)
    best = int(np.argmin(cv))
    mean, scale = _standardise(d)
    z = (d - mean) / scale
    ym = float(y.mean())
    coef = ridge_solve(z, y - ym, grid[best])
    return LinearPeer(
        name=name,
        lags=lags,
        lag_rows=lag_rows,
        mean=mean,
        scale=scale,
        coef=coef,
        intercept=ym,
        alpha=float(grid[best]),
        cv_mse=float(cv[best]),
        cv_curve=tuple(float(v) for v in cv),
    )


def fit_ridge(
    x: ArrayLike, y: ArrayLike, rows: ArrayLike, *, grid: Sequence[float] = RIDGE_GRID, folds: int = 5
) -> LinearPeer:
    """Ridge on the features at ``rows`` against the readings ``y`` (NaN: missing), λ by blocked CV."""
    xs, ys, r = _prepare(x, y, rows)
    return _fit_ridge_design("ridge", lagged(xs, r, 0, 1), ys, 0, 1, grid, folds)


def fit_arx(
    x: ArrayLike,
    y: ArrayLike,
    rows: ArrayLike,
    *,
    lag_rows: int,
    orders: Sequence[int] = ARX_LAGS,
    grid: Sequence[float] = RIDGE_GRID,
    folds: int = 5,
) -> LinearPeer:
    """The distributed-lag (ARX) peer: for each lag order the ridge with λ by blocked CV; the order with the
    smallest CV error wins."""
    xs, ys, r = _prepare(x, y, rows)
    fits = [
        _fit_ridge_design("arx", lagged(xs, r, lag, lag_rows), ys, lag, lag_rows, grid, folds)
        for lag in orders
    ]
    return min(fits, key=lambda f: f.cv_mse)


def _lasso_grid(z: Array, y: Array, n: int = LASSO_GRID_N) -> Array:
    lam_max = float(np.abs(z.T @ y).max()) / y.size
    return np.asarray(lam_max * np.logspace(0, -3, n)) if lam_max > 0 else np.array([0.0])


def fit_lasso(x: ArrayLike, y: ArrayLike, rows: ArrayLike, *, folds: int = 5) -> LinearPeer:
    """LASSO on the features at ``rows`` against ``y``, λ by blocked CV (the grid from the whole test's λ_max
    down to 1e-3 λ_max)."""
    xs, ys, r = _prepare(x, y, rows)
    d = lagged(xs, r, 0, 1)
    mean, scale = _standardise(d)
    z = (d - mean) / scale
    ym = float(ys.mean())
    grid = _lasso_grid(z, ys - ym)
    sse = np.zeros(grid.size)
    for test in blocked_folds(ys.size, folds):
        train = np.setdiff1d(np.arange(ys.size), test)
        m, s = _standardise(d[train])
        zt, zv = (d[train] - m) / s, (d[test] - m) / s
        yt = ys[train].mean()
        path = lasso_path(zt, ys[train] - yt, grid)
        sse += (((ys[test] - yt)[None, :] - path @ zv.T) ** 2).sum(axis=1)
    cv = sse / ys.size
    best = int(np.argmin(cv))
    coef = lasso_path(z, ys - ym, grid[: best + 1])[-1]
    return LinearPeer(
        name="lasso",
        lags=0,
        lag_rows=1,
        mean=mean,
        scale=scale,
        coef=coef,
        intercept=ym,
        alpha=float(grid[best]),
        cv_mse=float(cv[best]),
        cv_curve=tuple(float(v) for v in cv),
    )


def hold_flagged(temps_c: ArrayLike, status: ArrayLike) -> Array:
    """The temperatures with every reading the DAQ flags (status ≠ 0: open circuit, out of range) replaced by
    the channel's last unflagged one (before any: its first unflagged one; none at all: NaN) — what a
    regression's input stage does with a flagged channel."""
    t = np.asarray(temps_c, dtype=float).copy()
    bad = np.asarray(status) != 0
    for c in np.flatnonzero(bad.any(axis=0)):
        good = np.flatnonzero(~bad[:, c])
        if good.size == 0:
            t[:, c] = np.nan
            continue
        idx = np.maximum.accumulate(np.where(~bad[:, c], np.arange(t.shape[0]), -1))
        idx = np.where(idx < 0, good[0], idx)
        t[:, c] = t[idx, c]
    return t
