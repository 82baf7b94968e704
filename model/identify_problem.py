"""The least-squares problem behind the identification: residuals of the reduced model against a window.

Parameters θ are H1..H7 [W/(m²·K)], optionally followed by the front/rear bearing heat scale factors
(dimensionless) and by a uniform shift of the window's start field [°C] (``Layout``). The residual
r = T_model − T_measured [°C] is taken over the usable entries: channels in the window's mask, samples 1..n
(sample 0 is fixed by the initial field, not by H) and finite measurements. The objective is
f = mean(r²) [°C²] (the paper's eq. 32); the paper's fitness is 1/(1+f).

Everything is evaluated for a whole population at once (one reduced-model call per batch), including the
finite-difference Jacobian: the p perturbed points form one batch.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
N_H = 7


class SensorModel(Protocol):
    """What the identification needs of ``model.rom.ReducedModel``."""

    def simulate_sensors(
        self,
        h: Array,
        inputs: Any,
        t0: float | Array,
        *,
        load_scale: Array | None = None,
        t0_shift: Array | None = None,
    ) -> Array: ...


@dataclass(frozen=True)
class Layout:
    """Where the parameters sit in θ: H1..H7, then the two heat-load scales if ``loads``, then the start
    field's uniform shift [°C] if ``t0_shift``."""

    loads: bool = False
    t0_shift: bool = False

    @property
    def p(self) -> int:
        """Number of parameters."""
        return N_H + 2 * int(self.loads) + int(self.t0_shift)

    def load_scale(self, theta: Array) -> Array | None:
        """The load scales (..., 2) of θ (..., p), or None when they are not fitted."""
        return theta[..., N_H : N_H + 2] if self.loads else None

    def shift(self, theta: Array) -> Array | None:
        """The start-field shift (...,) [°C] of θ (..., p), or None when it is not fitted."""
        return theta[..., -1] if self.t0_shift else None


@dataclass(frozen=True)
class Usable:
    """Which entries of the (n_steps + 1, 32) window enter the fit."""

    entries: NDArray[np.bool_]  # (n_steps + 1, 32)

    @property
    def m(self) -> int:
        return int(self.entries.sum())

    @property
    def sensors(self) -> int:
        return int(self.entries.any(axis=0).sum())

    @property
    def samples(self) -> int:
        return int(self.entries.any(axis=1).sum())


def usable_entries(measured_c: Array, mask: NDArray[np.bool_]) -> Usable:
    """Entries used by the fit: masked-in channels, samples after the first, finite values."""
    entries = np.isfinite(measured_c) & np.asarray(mask, dtype=bool)[None, :]
    entries[0, :] = False
    return Usable(entries)


def baseline_offsets(baseline_c: ArrayLike, model_c: ArrayLike) -> Array:
    """Sensor offsets [°C] from a baseline at thermal equilibrium: mean measured − model, per channel.

    ``baseline_c`` is (n, 32) or (32,) measured at equilibrium (spindle idle long enough that every part sits
    at the ambient, or any state the model reproduces); ``model_c`` is the model's value there, a scalar
    (e.g. the ambient) or (32,). Subtract the result from later measurements (``identify(offsets_c=...)``).
    """
    base = np.atleast_2d(np.asarray(baseline_c, dtype=float))
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(base, axis=0)
    return np.asarray(mean - np.broadcast_to(np.asarray(model_c, dtype=float), mean.shape))


class Problem:
    """Batched residuals, objective and Jacobian of one identification window; counts model evaluations."""

    def __init__(
        self,
        model: SensorModel,
        *,
        inputs: Any,
        measured_c: Array,
        usable: Usable,
        t0: float | Array,
        bounds: Array,
        layout: Layout | None = None,
    ) -> None:
        self.layout = layout or Layout(loads=len(bounds) > N_H)
        if self.layout.p != len(bounds):
            raise ValueError(f"bounds: expected {self.layout.p} rows for {self.layout}, got {len(bounds)}")
        self.model = model
        self.inputs = inputs
        self.measured = measured_c
        self.usable = usable
        self.t0 = t0
        self.bounds = bounds
        self.p = len(bounds)
        self.nfev = 0
        self._flat = np.flatnonzero(usable.entries.ravel())
        self._target = measured_c.ravel()[self._flat]
        self._weights = usable.entries.astype(float) / max(usable.m, 1)
        self._filled = np.where(usable.entries, measured_c, 0.0)

    @classmethod
    def from_window(
        cls, model: SensorModel, window: Any, bounds: Array, layout: Layout | None = None
    ) -> Problem:
        """The problem of a ``model.identify.Window`` as measured (no offsets), over its usable entries."""
        return cls(
            model,
            inputs=window.inputs,
            measured_c=window.measured_c,
            usable=usable_entries(window.measured_c, window.mask),
            t0=window.t0,
            bounds=bounds,
            layout=layout,
        )

    def start(self, theta: Array, t0: float | Array | None = None) -> float | Array:
        """The start field [°C] (uniform or (N,)) for θ (p,): ``t0`` (default the window's) plus the fitted
        uniform shift, if any."""
        base = self.t0 if t0 is None else t0
        shift = self.layout.shift(theta)
        return base if shift is None else np.asarray(base, dtype=np.float64) + float(shift)

    def predict(self, theta: Array) -> Array:
        """Model sensor temperatures (P, n_steps + 1, 32) [°C] for parameters θ (P, p)."""
        theta = np.atleast_2d(theta)
        self.nfev += len(theta)
        lay = self.layout
        extra = {"t0_shift": lay.shift(theta)} if lay.t0_shift else {}  # stand-in models may lack the keyword
        return np.asarray(
            self.model.simulate_sensors(
                theta[:, :N_H], self.inputs, self.t0, load_scale=lay.load_scale(theta), **extra
            )
        )

    def residuals(self, theta: Array) -> Array:
        """r = model − measured over the usable entries, (P, m) [°C]."""
        return np.asarray(self.select(self.predict(theta)) - self._target[None, :])

    @property
    def channels(self) -> NDArray[np.int64]:
        """Channel index (0..n_channels-1) of each usable entry, in the residuals' order."""
        return np.asarray(self._flat % self.measured.shape[1], dtype=np.int64)

    def select(self, values: Array) -> Array:
        """The usable entries (K, m) of model-shaped values (K, n_steps + 1, 32), in the residuals' order."""
        flat = values.reshape(values.shape[0], int(np.prod(values.shape[1:])))  # also for K = 0
        return np.asarray(flat[:, self._flat])

    def objective(self, theta: Array) -> Array:
        """f = mean(r²) per candidate, (P,) [°C²]; suited as a vectorized optimizer objective."""
        diff = self.predict(theta) - self._filled[None, :, :]
        diff *= diff
        return np.asarray(np.einsum("pij,ij->p", diff, self._weights))

    def jacobian(
        self, theta: Array, r0: Array | None = None, *, rel_step: float = 1e-6
    ) -> tuple[Array, Array]:
        """(J (m, p) [°C per unit θ], r (m,)) by forward differences, all points in one model call.

        Steps go backwards where a forward step would leave the box.
        """
        x = np.asarray(theta, dtype=float)
        step = rel_step * np.maximum(np.abs(x), 1.0)
        step = np.where(x + step > self.bounds[:, 1], -step, step)
        pts = x[None, :] + np.diag(step)
        if r0 is None:
            pts = np.vstack([x[None, :], pts])
        res = self.residuals(pts)
        base = res[0] if r0 is None else r0
        diffs = res[1:] if r0 is None else res
        return np.asarray(((diffs - base[None, :]) / step[:, None]).T), np.asarray(base)


@dataclass(frozen=True)
class Confidence:
    """Linearised statistics at the optimum: cov = σ²(JᵀJ)⁻¹ with σ² = SSR/(m − p)."""

    sigma_c: float
    cov: Array  # (p, p)
    half_width: Array  # (p,) 95 % half-widths
    correlation: Array  # (p, p)


def confidence(
    jac: Array, residual: Array, *, z: float = 1.959964, prior_information: Array | None = None
) -> Confidence:
    """95 % confidence from the Jacobian (m, p) and residuals (m,) at the optimum (pinv if singular).

    With ``prior_information`` P (p, p) (a Gaussian prior's, ``model.identify_prior``) the posterior's:
    cov = (JᵀJ/σ² + P)⁻¹ = σ²·(JᵀJ + σ²P)⁻¹, σ from the data's residuals alone."""
    m, p = jac.shape
    ssr = float(residual @ residual)
    sigma2 = ssr / max(m - p, 1)
    normal = jac.T @ jac
    if prior_information is not None:
        normal = normal + sigma2 * np.asarray(prior_information)
    return with_cov(float(np.sqrt(sigma2)), sigma2 * np.linalg.pinv(normal), z=z)


def channel_bias_cov(
    jac: Array, channels: NDArray[np.int64], sd_c: Array, *, normal: Array | None = None
) -> Array:
    """θ's covariance (p, p) from an unknown constant bias per channel with standard deviation ``sd_c`` (32,)
    [°C]: a sensor offset left after (or without) a baseline, and the model error's slow part.

    A bias b_c on channel c shifts the residuals of that channel's entries by b_c; the least-squares answer
    moves by δθ = −(JᵀJ)⁺·Jᵀ·B·b with B (m, 32) the entries' channel indicator, so cov = G·diag(sd²)·Gᵀ with
    G = (JᵀJ)⁺·Jᵀ·B. Unlike the noise this does not average out over the window, which is why it goes into
    the covariance rather than into σ. ``channels`` (m,) is the channel index (0..31) of each residual entry;
    ``normal`` (p, p) replaces JᵀJ (a MAP fit's JᵀJ + σ²P: its answer moves less).
    """
    per_channel = np.zeros((jac.shape[1], sd_c.size))
    np.add.at(per_channel.T, channels, jac)  # Jᵀ·B: the sum of each channel's Jacobian rows
    normal = jac.T @ jac if normal is None else normal
    gain = np.linalg.pinv(normal) @ per_channel * sd_c[None, :]
    return np.asarray(gain @ gain.T)


def with_cov(sigma_c: float, cov: Array, *, z: float = 1.959964) -> Confidence:
    """95 % half-widths and correlation of a parameter covariance (p, p) (e.g. widened by ``model.carry``)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    return Confidence(sigma_c, cov, z * sd, corr)


def per_sensor_rmse(pred: Array, measured: Array, *, skip_first: bool = True) -> Array:
    """RMSE per channel (32,) [°C] over the finite samples (NaN for a channel without any)."""
    err = (pred - measured)[1:] if skip_first else pred - measured
    sq = err * err
    n = np.isfinite(sq).sum(axis=0)
    total = np.where(np.isfinite(sq), sq, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(n > 0, np.sqrt(total / np.maximum(n, 1)), np.nan))


def point_errors(
    pred: Array, measured: Array, channels: Mapping[int, int], *, skip_first: bool = True
) -> dict[int, dict[str, float]]:
    """Paper's Table 11 metrics per test point: max |error|, mean |error| and RMSE [°C].

    ``channels`` maps test point -> 1-based channel.
    """
    err = (pred - measured)[1:] if skip_first else pred - measured
    out: dict[int, dict[str, float]] = {}
    for tp, ch in sorted(channels.items()):
        e = err[:, ch - 1]
        e = e[np.isfinite(e)]
        if e.size == 0:
            continue
        out[tp] = {
            "me": float(np.max(np.abs(e))),
            "mae": float(np.mean(np.abs(e))),
            "rmse": float(np.sqrt(np.mean(e * e))),
        }
    return out
