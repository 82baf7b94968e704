"""The literature's peer: a multiple linear regression (MLR) thermal-error model (issue 27 item 4).

The classic recipe: pick a few key temperature sensors by correlation clustering (hierarchical clustering,
average linkage, of the distance 1 − |corr| between the sensors over the commissioning run; in each cluster
the sensor most correlated with the displacement), then fit the displacement [µm] as an intercept plus a
linear combination of those temperatures [°C] by least squares on the same run, and predict on another run.

Pure: numpy and scipy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.errors import ModelError

__all__ = ["MlrError", "MlrModel", "fit_mlr", "select_sensors"]


class MlrError(ModelError, ValueError):
    """Bad input to the MLR fit (shapes, too few rows, constant data)."""


@dataclass(frozen=True)
class MlrModel:
    """``sensors`` (column indices into the 32), ``coef`` [µm/°C] per sensor, ``intercept`` [µm], the
    clusters (sensor indices per cluster) and the fit's residual RMS [µm] on the commissioning run."""

    sensors: tuple[int, ...]
    coef: NDArray[np.float64]
    intercept: float
    clusters: tuple[tuple[int, ...], ...]
    residual_rms_um: float

    def predict(self, temps_c: ArrayLike) -> NDArray[np.float64]:
        """The displacement [µm] for each row of ``temps_c`` (rows × all sensors, °C)."""
        t = np.asarray(temps_c, dtype=float)
        if t.ndim != 2 or t.shape[1] <= max(self.sensors):
            raise MlrError(f"temps_c: need rows × >{max(self.sensors)} sensors, got shape {t.shape}")
        return np.asarray(t[:, list(self.sensors)] @ self.coef + self.intercept, dtype=float)


def _abs_corr(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """|corr| of each column of ``x`` with ``y`` (0 for a constant column)."""
    xc, yc = x - x.mean(axis=0), y - y.mean()
    den = np.sqrt((xc**2).sum(axis=0) * (yc**2).sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(den > 0, np.abs(xc.T @ yc) / np.where(den > 0, den, 1.0), 0.0)
    return np.asarray(r, dtype=float)


def select_sensors(
    temps_c: ArrayLike, disp_um: ArrayLike, *, n_clusters: int = 5
) -> tuple[tuple[int, ...], tuple[tuple[int, ...], ...]]:
    """The key sensors (one per cluster, the most correlated with ``disp_um``, in cluster order) and the
    clusters: average-linkage hierarchical clustering of 1 − |corr| between the columns of ``temps_c``
    (rows × sensors, °C), cut into ``n_clusters``. Constant sensors are left out."""
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    t, d = _check(temps_c, disp_um)
    live = np.flatnonzero(t.std(axis=0) > 0)
    if live.size < n_clusters or n_clusters < 1:
        raise MlrError(f"n_clusters: need 1..{live.size} (non-constant sensors), got {n_clusters}")
    tl = t[:, live]
    corr = np.corrcoef(tl, rowvar=False)
    dist = np.clip(1.0 - np.abs(corr), 0.0, None)
    np.fill_diagonal(dist, 0.0)
    dist = 0.5 * (dist + dist.T)
    labels = fcluster(linkage(squareform(dist, checks=False), method="average"), n_clusters, "maxclust")
    r = _abs_corr(tl, d)
    clusters, picks = [], []
    for lab in sorted(set(labels.tolist())):
        members = np.flatnonzero(labels == lab)
        clusters.append(tuple(int(live[m]) for m in members))
        picks.append(int(live[members[np.argmax(r[members])]]))
    return tuple(picks), tuple(clusters)


def fit_mlr(temps_c: ArrayLike, disp_um: ArrayLike, *, n_clusters: int = 5) -> MlrModel:
    """Select the sensors (``select_sensors``) and fit ``disp_um`` ≈ intercept + Σ coef·T by least squares
    over the rows where ``disp_um`` is finite."""
    t, d = _check(temps_c, disp_um)
    sensors, clusters = select_sensors(t, d, n_clusters=n_clusters)
    a = np.column_stack([t[:, list(sensors)], np.ones(d.size)])
    sol, *_ = np.linalg.lstsq(a, d, rcond=None)
    resid = d - a @ sol
    return MlrModel(
        sensors=sensors,
        coef=np.asarray(sol[:-1], dtype=float),
        intercept=float(sol[-1]),
        clusters=clusters,
        residual_rms_um=float(np.sqrt(np.mean(resid**2))),
    )


def _check(temps_c: ArrayLike, disp_um: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rows with a finite displacement and finite temperatures."""
    t, d = np.asarray(temps_c, dtype=float), np.asarray(disp_um, dtype=float)
    if t.ndim != 2 or d.ndim != 1 or t.shape[0] != d.size:
        raise MlrError(f"temps_c (rows × sensors) and disp_um (rows) disagree: {t.shape} vs {d.shape}")
    ok = np.isfinite(d) & np.isfinite(t).all(axis=1)
    if ok.sum() < t.shape[1] // 4 + 3:
        raise MlrError(f"too few finite rows: {int(ok.sum())}")
    return t[ok], d[ok]
