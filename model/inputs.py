"""Time-varying inputs of the thermal model: ambient temperature and bearing heats per time step.

Errors::

    InputError(ValueError)   arrays of different lengths, non-finite values, bad dt
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from model.errors import ModelError
from model.geometry import SpindleSpec
from model.heat import bearing_heat_w


class InputError(ModelError, ValueError):
    """Inconsistent model inputs; the message names the field."""


@dataclass(frozen=True)
class InputSeries:
    """Piecewise-constant inputs: entry k applies on step k -> k+1; all arrays have length n_steps.

    dt_s: step [s]; ambient_c: ambient Ti [degC]; q_front_w, q_rear_w: bearing heats [W].
    """

    dt_s: float
    ambient_c: NDArray[np.float64]
    q_front_w: NDArray[np.float64]
    q_rear_w: NDArray[np.float64]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dt_s) and self.dt_s > 0):
            raise InputError(f"dt_s: must be > 0, got {self.dt_s!r}")
        n = len(self.ambient_c)
        for name in ("ambient_c", "q_front_w", "q_rear_w"):
            a = getattr(self, name)
            if a.ndim != 1 or len(a) != n:
                raise InputError(f"{name}: must be 1-D of length {n} (n_steps), got shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise InputError(f"{name}: contains non-finite values")

    @property
    def n_steps(self) -> int:
        """Number of time steps."""
        return len(self.ambient_c)

    @property
    def times_s(self) -> NDArray[np.float64]:
        """Time of each state, 0 .. n_steps * dt_s [s] (length n_steps + 1)."""
        return np.arange(self.n_steps + 1, dtype=np.float64) * self.dt_s

    @classmethod
    def constant(
        cls, n_steps: int, *, dt_s: float, ambient_c: float, q_front_w: float, q_rear_w: float
    ) -> InputSeries:
        """Constant inputs over ``n_steps`` steps of ``dt_s`` [s]."""
        ones = np.ones(int(n_steps))
        return cls(float(dt_s), ambient_c * ones, q_front_w * ones, q_rear_w * ones)

    def slice(self, start: int, stop: int) -> InputSeries:
        """Steps start..stop-1 as a new series."""
        return InputSeries(
            self.dt_s, self.ambient_c[start:stop], self.q_front_w[start:stop], self.q_rear_w[start:stop]
        )


def _per_step(value: ArrayLike, name: str, n: int | None) -> NDArray[np.float64]:
    a = np.atleast_1d(np.asarray(value, dtype=float))
    if a.ndim != 1:
        raise InputError(f"{name}: must be a scalar or 1-D array")
    if n is not None and a.size == 1:
        a = np.full(n, a[0])
    return a


def inputs_from_operation(
    spec: SpindleSpec, *, dt_s: float, speed_rpm: ArrayLike, torque_nm: ArrayLike, ambient_c: ArrayLike
) -> InputSeries:
    """Inputs per step from the operating condition (speed [rpm], torque [N m], ambient [degC]).

    Each argument is a scalar or an array of length n_steps; at least one must be an array unless all are
    scalars (then n_steps = 1). Bearing heats come from ``model.heat.bearing_heat_w``.
    """
    lengths = {np.size(v) for v in (speed_rpm, torque_nm, ambient_c) if np.ndim(v) > 0}
    if len(lengths) > 1:
        raise InputError(f"speed_rpm/torque_nm/ambient_c: array lengths differ ({sorted(lengths)})")
    n = lengths.pop() if lengths else 1
    n_ = _per_step(speed_rpm, "speed_rpm", n)
    t_ = _per_step(torque_nm, "torque_nm", n)
    a_ = _per_step(ambient_c, "ambient_c", n)
    qf = np.asarray(bearing_heat_w(n_, t_, spec.bearings.front), dtype=float)
    qr = np.asarray(bearing_heat_w(n_, t_, spec.bearings.rear), dtype=float)
    return InputSeries(float(dt_s), a_, qf, qr)
