"""The speed map's state in the service: the latest H map fit (``model.hmap_identify.MapFit``'s posterior),
the speeds the data have covered, and its configuration (``identification.mode = "speed_map"``).

Pure numpy (``model.hmap`` only): the core keeps a :class:`SpeedMap` (frozen, published in its view), the
API threads evaluate it (``h_at``: microseconds), the database stores it as JSON in the identification's
diagnostics (``to_json`` / ``from_json``) and a restart restores it as stale.

Visited speeds (``VisitTally``): every sample's speed is binned (``MapConfig.bin_rpm``) and its seconds
accumulated, decaying with the same factor e^(−Δt/τ) as the map's information (``forget``), so a speed
visited hours ago stops counting as covered when its information has mostly been forgotten; a fit's map
carries the tally at its window's end (the data the fits so far have seen).

Errors::

    SpeedMapError(ValueError)   a bad stored map or configuration (the field is named)
"""

from __future__ import annotations

import base64
import binascii
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from model.hmap import Family
from service.errors import ServiceError

__all__ = [
    "MAP_BIN_RPM",
    "MAP_GRID_RPM",
    "MapConfig",
    "SpeedMap",
    "SpeedMapError",
    "VisitTally",
    "beyond_box",
]


FloatArray = npt.NDArray[np.float64]
MAP_GRID_RPM: FloatArray = np.arange(0.0, 7000.0 + 1.0, 100.0)  # the grid chtc_map() serves
MAP_GRID_RPM.setflags(write=False)
MIN_VISITED_S = 1.0  # accumulated seconds below this: forgotten
MAP_BIN_RPM = 50.0  # visited speeds are binned to this (MapConfig.bin_rpm; no settings key)


def beyond_box(lo: npt.ArrayLike, hi: npt.ArrayLike, box: tuple[float, float]) -> npt.NDArray[np.bool_]:
    """Which H's 95 % band ``lo``..``hi`` [W/(m²·K)] lies wholly outside ``box`` (the reduced model's H box,
    ``model.rom``'s ``h_box``): there the map extrapolated beyond where the live state's model holds (its
    level bounds are 0.5–500 W/(m²·K)), so such an H is a guess, never identified, and the live state takes it
    with the guessed considered error (``service.core.maptrack.into_box``; docs/design/robustness.md)."""
    box_lo, box_hi = float(box[0]), float(box[1])
    return np.asarray(
        (np.asarray(hi, dtype=np.float64) < box_lo) | (np.asarray(lo, dtype=np.float64) > box_hi), dtype=bool
    )


class SpeedMapError(ServiceError, ValueError):
    """A bad stored speed map or map configuration; the message names the field."""


@dataclass(frozen=True, kw_only=True)
class MapConfig:
    """The speed map mode's knobs (``identification.map_*`` and ``experimental.map_*`` settings, no defaults
    here: ``service.core.config.map_config`` builds it; times in s, speeds in rpm).

    window_s: the rolling window of recent data each fit uses (60 min measured, docs/design/hmap.md);
    min_window_s: the shortest window fitted (a cold start waits this long);
    debounce_s: after a confirmed condition change, wait this long without another change before fitting;
    refit_s: fit again after this long without a change (a long hold keeps the map current);
    fresh_s: a map whose window ended longer ago than this is not fresh;
    margin_rpm: a speed within this of a visited one counts as covered (fresh);
    min_visit_s: seconds of (decayed) data at a speed bin before it counts as visited;
    bin_rpm: visited speeds are binned to this;
    tau_h: forgetting time of ``model.hmap_identify.forget`` (h);
    family: "nodes" | "physics" (``model.hmap``);
    prior_weight: covariance intersection of the fit's prior and start field (ω in (0, 1]; 1: independent):
    the prior's covariance is divided by ω and the start covariance by 1 − ω (docs/design/hmap.md);
    prior_level_sd: σ of the cold prior's overall ln H level per zone (``model.hmap.Family.prior``).
    """

    window_s: float
    min_window_s: float
    debounce_s: float
    refit_s: float
    fresh_s: float
    margin_rpm: float
    min_visit_s: float
    bin_rpm: float  # MAP_BIN_RPM
    tau_h: float
    family: Literal["nodes", "physics"]
    prior_weight: float
    prior_level_sd: float

    def __post_init__(self) -> None:
        for name in ("window_s", "min_window_s", "refit_s", "fresh_s", "bin_rpm", "tau_h"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise SpeedMapError(f"MapConfig.{name}: must be > 0, got {v}")
        for name in ("debounce_s", "margin_rpm", "min_visit_s", "prior_level_sd"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise SpeedMapError(f"MapConfig.{name}: must be >= 0, got {v}")
        if self.min_window_s > self.window_s:
            raise SpeedMapError(
                f"MapConfig.min_window_s ({self.min_window_s}) must be <= window_s ({self.window_s})"
            )
        if not (0.0 < float(self.prior_weight) <= 1.0):
            raise SpeedMapError(f"MapConfig.prior_weight: must be in (0, 1], got {self.prior_weight}")
        if self.family not in ("nodes", "physics"):
            raise SpeedMapError(f"MapConfig.family: expected 'nodes' or 'physics', got {self.family!r}")


def _ro(a: Any, shape: tuple[int, ...] | None = None, name: str = "array") -> FloatArray:
    out = np.array(a, dtype=np.float64)
    if shape is not None and out.shape != shape:
        raise SpeedMapError(f"SpeedMap.{name}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise SpeedMapError(f"SpeedMap.{name}: must be finite")
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False, kw_only=True)
class SpeedMap:
    """One map fit as the service keeps it: θ's posterior ``mean`` (p,) and ``cov`` (p, p) of ``family``,
    the accumulated visited speeds [rpm] and seconds, the UTC end of the fit's window (``fitted_at``), the
    stored identification's id, the fit's RMS residual [°C], and whether it was restored from the database
    (not re-fitted since the restart)."""

    family: Literal["nodes", "physics"]
    mean: FloatArray
    cov: FloatArray
    visited_rpm: FloatArray
    visited_s: FloatArray
    fitted_at: datetime
    identification_id: int | None = None
    rmse_c: float | None = None
    restored: bool = False

    def __post_init__(self) -> None:
        fam = Family(self.family)
        p = fam.n_theta
        object.__setattr__(self, "mean", _ro(self.mean, (p,), "mean"))
        object.__setattr__(self, "cov", _ro(self.cov, (p, p), "cov"))
        rpm = _ro(self.visited_rpm, None, "visited_rpm")
        sec = _ro(self.visited_s, rpm.shape, "visited_s")
        if rpm.ndim != 1:
            raise SpeedMapError(f"SpeedMap.visited_rpm: expected (m,), got {rpm.shape}")
        object.__setattr__(self, "visited_rpm", rpm)
        object.__setattr__(self, "visited_s", sec)
        if self.fitted_at.tzinfo is None:
            raise SpeedMapError("SpeedMap.fitted_at: must be timezone-aware UTC")

    @property
    def model_family(self) -> Family:
        return Family(self.family)

    def h_at(self, speed_rpm: Any, ambient_c: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
        """H and its 95 % band, each (S, 7) W/(m²·K), at speeds (S,) [rpm] and ambient [°C]."""
        return self.model_family.h_ci95_at(self.mean, self.cov, np.abs(np.atleast_1d(speed_rpm)), ambient_c)

    def covered(self, speed_rpm: float, *, margin_rpm: float, min_visit_s: float) -> bool:
        """Whether ``speed_rpm`` lies within ``margin_rpm`` of a speed with >= ``min_visit_s`` of data."""
        ok = self.visited_s >= min_visit_s
        if not ok.any():
            return False
        return bool(np.min(np.abs(self.visited_rpm[ok] - abs(float(speed_rpm)))) <= margin_rpm + 1e-9)

    def to_json(self) -> dict[str, Any]:
        """What the identification row's diagnostics carry (``"speed_map"``): plain lists, and the covariance
        as its upper triangle, row by row, little-endian float64 in base64 (``cov_upper_b64``: exact; the
        tabulated family's map is 18 kB of JSON, ~74 kB with the covariance as a list of lists)."""
        upper = self.cov[np.triu_indices(self.mean.size)].astype("<f8")
        return {
            "family": self.family,
            "mean": [float(x) for x in self.mean],
            "cov_upper_b64": base64.b64encode(upper.tobytes()).decode("ascii"),
            "visited_rpm": [float(x) for x in self.visited_rpm],
            "visited_s": [float(x) for x in self.visited_s],
            "fitted_at": self.fitted_at.astimezone(UTC).isoformat(),
            "rmse_c": self.rmse_c,
        }

    @classmethod
    def from_json(cls, data: Any, *, identification_id: int | None, restored: bool = True) -> SpeedMap:
        """The map stored by ``to_json`` (also the earlier form with ``cov`` as a list of lists); raises
        SpeedMapError naming a missing or bad field."""
        if not isinstance(data, dict):
            raise SpeedMapError(f"speed_map: expected an object, got {type(data).__name__}")
        try:
            fitted = datetime.fromisoformat(str(data["fitted_at"]))
            rmse = data.get("rmse_c")
            mean = np.asarray(data["mean"], dtype=float)
            return cls(
                family=data["family"],
                mean=mean,
                cov=_cov_of(data, mean.size),
                visited_rpm=np.asarray(data["visited_rpm"], dtype=float),
                visited_s=np.asarray(data["visited_s"], dtype=float),
                fitted_at=fitted,
                identification_id=identification_id,
                rmse_c=None if rmse is None else float(rmse),
                restored=restored,
            )
        except KeyError as err:
            raise SpeedMapError(f"speed_map.{err.args[0]}: missing") from err
        except (TypeError, ValueError) as err:
            if isinstance(err, SpeedMapError):
                raise
            raise SpeedMapError(f"speed_map: {err}") from err


def _cov_of(data: dict[str, Any], p: int) -> FloatArray:
    """The symmetric (p, p) covariance from ``to_json``'s ``cov_upper_b64`` (or the earlier ``cov`` lists)."""
    if "cov" in data:
        return np.asarray(data["cov"], dtype=float)
    try:
        raw = base64.b64decode(str(data["cov_upper_b64"]), validate=True)
    except binascii.Error as err:
        raise SpeedMapError(f"speed_map.cov_upper_b64: not base64 ({err})") from err
    n = p * (p + 1) // 2
    if len(raw) != 8 * n:
        raise SpeedMapError(
            f"speed_map.cov_upper_b64: {len(raw)} bytes, expected {8 * n} (the upper triangle of {p}x{p})"
        )
    cov = np.zeros((p, p))
    cov[np.triu_indices(p)] = np.frombuffer(raw, dtype="<f8")
    return cov + np.triu(cov, 1).T


class VisitTally:
    """Seconds of data per speed bin, accumulated sample by sample and decayed with e^(−Δt/τ) (the map's
    forgetting): what the fits so far have seen. Mutable; the core owns one and snapshots it (``visited``)
    when a fit's window ends."""

    def __init__(self, *, bin_rpm: float, tau_h: float) -> None:
        self._bin = float(bin_rpm)
        self._tau_s = 3600.0 * float(tau_h)
        self._sec: dict[float, float] = {}
        self._t: float | None = None

    def add(self, t: float, speed_rpm: float, dt_s: float) -> None:
        """One sample at epoch ``t`` s, at ``speed_rpm``, standing for ``dt_s`` seconds (non-finite speed:
        nothing counted, the decay still runs)."""
        if self._t is not None and t > self._t:
            f = float(np.exp(-(t - self._t) / self._tau_s))
            self._sec = {k: v * f for k, v in self._sec.items() if v * f >= MIN_VISITED_S}
        self._t = t if self._t is None else max(self._t, t)
        if np.isfinite(speed_rpm):
            k = float(np.round(abs(speed_rpm) / self._bin) * self._bin)
            self._sec[k] = self._sec.get(k, 0.0) + float(dt_s)

    def visited(self) -> tuple[FloatArray, FloatArray]:
        """Bin centres (m,) [rpm] ascending and seconds (m,)."""
        keys = sorted(self._sec)
        return np.array(keys, dtype=float), np.array([self._sec[k] for k in keys], dtype=float)

    def restore(self, rpm: Any, seconds: Any, t: float) -> None:
        """Start from a stored map's visited speeds at epoch ``t``."""
        self._sec = {float(k): float(v) for k, v in zip(rpm, seconds, strict=True)}
        self._t = t
