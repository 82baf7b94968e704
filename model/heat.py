"""Bearing friction heat from speed and torque (Palmgren), SPEC section 2.

Q = 1.047e-4 * n * M   [W; n in rpm, M in N mm]
M = M0 + M1
M0 = 1e-7 * f0 * (nu * n)^(2/3) * dm^3   if nu * n >= 2000, else 160e-7 * f0 * dm^3   [N mm]
M1 = f1 * P1 * dm                                                                    [N mm]

How the measured spindle torque enters: the cutting torque T [N m] loads the bearings through the cutting
force, so the equivalent load grows with it: P1 = p1_n + load_per_torque_n_per_nm * |T| (both per bearing set,
from the spindle TOML). Speed is taken as |n| (direction does not matter).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.geometry import BearingSpec

RPM_NMM_TO_W = 1.047e-4  # 2 pi / 60 / 1000: W per (rpm * N mm)


def load_n(torque_nm: ArrayLike, bearing: BearingSpec) -> NDArray[np.float64]:
    """Equivalent bearing load P1 [N] for a measured spindle torque [N m]."""
    return bearing.p1_n + bearing.load_per_torque_n_per_nm * np.abs(np.asarray(torque_nm, dtype=float))


def friction_moment_nmm(
    speed_rpm: ArrayLike, torque_nm: ArrayLike, bearing: BearingSpec
) -> NDArray[np.float64]:
    """Palmgren friction moment M = M0 + M1 [N mm] of one bearing set at speed [rpm] and torque [N m]."""
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    nu_n = bearing.nu_mm2_s * n
    dm3 = bearing.dm_mm**3
    m0 = np.where(nu_n >= 2000.0, 1e-7 * bearing.f0 * np.cbrt(nu_n) ** 2 * dm3, 160e-7 * bearing.f0 * dm3)
    m1 = bearing.f1 * load_n(torque_nm, bearing) * bearing.dm_mm
    return np.asarray(m0 + m1, dtype=float)


def bearing_heat_w(
    speed_rpm: ArrayLike, torque_nm: ArrayLike, bearing: BearingSpec
) -> float | NDArray[np.float64]:
    """Friction heat Q [W] of one bearing set at speed [rpm] and spindle torque [N m]; float for scalars."""
    n = np.abs(np.asarray(speed_rpm, dtype=float))
    q = RPM_NMM_TO_W * n * friction_moment_nmm(n, torque_nm, bearing)
    return float(q) if q.ndim == 0 else q
