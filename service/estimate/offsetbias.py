"""What the sensors' unknown offsets do to the filtered live state: their share of its error (pure).

The filter (``model.estimator``) takes each sample's 32 readings as independent of the last: the unknown
part of the per-channel offsets (``FilteredState.set_offsets``' 1σ, 0.17 °C before a baseline) only widens
R. But an offset is the same in every sample, so the filter averages it as if it were noise and becomes sure
of a field it has bent towards the offsets: where the sensors cannot see, the shaft's inside, the bent part
stays, and is only slowly relaxed by the heat paths. At rest after a start, with ±0.2 °C offsets, the axial
growth was served 0.4 µm off with a 95 % CI of ±0.27 µm (issue 26).

The state's error has a part S·b, linear in the constant offset errors b (32,) [°C], 1σ ``sd`` each
(Schmidt's "consider" treatment of b: the filter's gain is left as it is; Simon 2006, 7.4). S (r, 32) follows
the filter: a prediction S ← A·S; an update with gain K over the used channels u: S ← (I − K·C_u)·S + K·E_u
(E_u picks the used channels). When a new baseline changes the offsets, the part absorbed so far becomes an
ordinary state error with covariance M = S·Σ·Sᵀ; it is propagated like one (M ← A·M·Aᵀ, then
(I − K·C)·M·(I − K·C)ᵀ), so data that see it shrink it, and the new offsets' part starts from S = 0. The
served covariance is P + M + S·Σ·Sᵀ (``extra_cov``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["OffsetBias", "kalman_gain"]

Array = NDArray[np.float64]


def kalman_gain(cov: Array, sensors: Array, use: NDArray[np.bool_], r_var: float) -> Array:
    """K (r, m) = P·Cᵀ·(C·P·Cᵀ + r·I)⁻¹ over the ``use``-d channels (m of them) of ``sensors`` C (32, r)."""
    c = sensors[use]
    pc = cov @ c.T
    s = c @ pc + r_var * np.eye(c.shape[0])
    return np.asarray(np.linalg.solve(s, pc.T).T)


class OffsetBias:
    """S, Σ and M of the module docstring for a reduced state of size ``r`` and ``n_channels`` sensors."""

    def __init__(self, r: int, n_channels: int = 32) -> None:
        self.r, self.n = int(r), int(n_channels)
        self.sd: Array = np.zeros(self.n)  # 1σ [°C] of the offsets' unknown part now
        self.restart()

    def restart(self) -> None:
        """A new start of the state (its prior knows nothing of the offsets): S = 0, M = 0."""
        self.s: Array = np.zeros((self.r, self.n))
        self.m: Array = np.zeros((self.r, self.r))

    def set_sd(self, sd_c: ArrayLike) -> None:
        """New offsets with unknown part 1σ ``sd_c`` (32,) [°C] (non-finite: 0): the part of the old ones
        absorbed so far becomes M; S restarts."""
        sd = np.nan_to_num(np.asarray(sd_c, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        if sd.shape != (self.n,) or np.any(sd < 0.0):
            raise ValueError(f"sd_c: expected {self.n} values >= 0 °C, got shape {sd.shape}")
        self.m = self.m + self._absorbed()
        self.s = np.zeros((self.r, self.n))
        self.sd = sd

    def predict(self, a: Array) -> None:
        """One step of the state's transition matrix A (r, r)."""
        self.s = a @ self.s
        self.m = a @ self.m @ a.T

    def update(self, gain: Array, sensors: Array, use: NDArray[np.bool_]) -> None:
        """An update with gain K (r, m) over the ``use``-d channels of ``sensors`` C (32, r)."""
        if not use.any():
            return
        ikc = np.eye(self.r) - gain @ sensors[use]
        s = ikc @ self.s
        s[:, use] += gain
        self.s = s
        self.m = ikc @ self.m @ ikc.T

    def charge(self, channel: int, bias_c: float) -> None:
        """Channel ``channel`` (0-based) was off by about ``bias_c`` [°C] while used (a drifting or stuck
        sensor, found and left out now): its part S[:, channel]·b becomes a state error of 1σ |b| in M (a
        constant offset's sensitivity: a drift grown to b bent the state less: on the safe side)."""
        b = float(bias_c)
        if not (0 <= channel < self.n and np.isfinite(b)):
            raise ValueError(f"charge: channel 0..{self.n - 1} and a finite bias_c, got {channel}, {bias_c}")
        col = self.s[:, channel]
        self.m = self.m + b * b * np.outer(col, col)

    def _absorbed(self) -> Array:
        return np.asarray((self.s * self.sd[None, :] ** 2) @ self.s.T)

    def extra_cov(self) -> Array:
        """M + S·Σ·Sᵀ (r, r) [°C²]: the offsets' share of the state's error covariance."""
        out = self.m + self._absorbed()
        return np.asarray(0.5 * (out + out.T))
