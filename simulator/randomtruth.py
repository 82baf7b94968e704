"""Seeded random smooth truths H(speed) for the virtual plant (``python -m benchmarks compensation``).

Per zone i, with x = 2·n/7000 − 1 the speed n [rpm] scaled to [−1, 1] (clamped outside 0–7000 rpm)::

    f_i(x)    = ln(H_REF_i) + c_i + a_i1·T1(x) + a_i2·T2(x) + a_i3·T3(x)     (Chebyshev polynomials T_k)
    ln H_i(n) = m + w · tanh((f_i(x) − m) / w)                              (m ± w: ln of the box 8–180)

``H_REF`` is the paper's Table 4 (3000 rpm); the level shift c_i ~ U(ln 0.6, ln 1.6); the slope
a_i1 ~ N(0.15, 0.25) (mostly rising with speed, as forced convection does, not always), the curvature terms
a_i2 ~ N(0, 0.15), a_i3 ~ N(0, 0.07). The tanh keeps every H strictly inside 8–180 W/(m²·K) without a kink
(it is nearly the identity in the middle of the box). The curve depends on the speed only (not on the ambient
or the torque). It shares nothing with ``model.plant.h_true`` (which is the paper's two tables joined by a
tanh in speed): a truth drawn here appears nowhere in the service's model, priors or other benches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import chebyshev
from numpy.typing import ArrayLike, NDArray

__all__ = ["H_BOX", "H_REF", "SPEED_MAX_RPM", "RandomTruth", "draw_truth"]

H_REF = np.array([88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54])  # paper Table 4 [W/(m²·K)]
H_BOX = (8.0, 180.0)  # W/(m²·K): every drawn H lies strictly inside
SPEED_MAX_RPM = 7000.0
_SHIFT = (np.log(0.6), np.log(1.6))
_SLOPE = (0.15, 0.25)  # mean, sd of a_i1
_CURVE_SD = (0.15, 0.07)  # sd of a_i2, a_i3


@dataclass(frozen=True)
class RandomTruth:
    """One drawn truth: Chebyshev coefficients ``coef`` (7, 4) of f_i (``__call__`` gives H)."""

    coef: NDArray[np.float64]

    def log_h(self, speed_rpm: ArrayLike) -> NDArray[np.float64]:
        """ln H (…, 7) at ``speed_rpm`` (any shape; |speed| used, clamped to 0–7000 rpm)."""
        n = np.clip(np.abs(np.asarray(speed_rpm, dtype=float)), 0.0, SPEED_MAX_RPM)
        x = 2.0 * n / SPEED_MAX_RPM - 1.0
        f = np.stack([chebyshev.chebval(x, c) for c in self.coef], axis=-1)
        mid = 0.5 * (np.log(H_BOX[0]) + np.log(H_BOX[1]))
        half = 0.5 * (np.log(H_BOX[1]) - np.log(H_BOX[0]))
        return np.asarray(mid + half * np.tanh((f - mid) / half))

    def __call__(
        self, speed_rpm: float, ambient_c: float = 0.0, torque_nm: float = 0.0
    ) -> NDArray[np.float64]:
        """H1..H7 (7,) [W/(m²·K)] at ``speed_rpm``: the plant's ``h_law`` signature (ambient and torque do not
        change this truth)."""
        del ambient_c, torque_nm
        return np.asarray(np.exp(self.log_h(float(speed_rpm))))


def draw_truth(rng: np.random.Generator) -> RandomTruth:
    """A truth drawn with ``rng`` (module docstring)."""
    coef = np.zeros((7, 4))
    coef[:, 0] = np.log(H_REF) + rng.uniform(*_SHIFT, 7)
    coef[:, 1] = rng.normal(_SLOPE[0], _SLOPE[1], 7)
    coef[:, 2] = rng.normal(0.0, _CURVE_SD[0], 7)
    coef[:, 3] = rng.normal(0.0, _CURVE_SD[1], 7)
    return RandomTruth(coef)
