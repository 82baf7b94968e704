"""What the live state's readers share: ``LiveStateError`` and the steady field of a live view.

The live state itself is the filtered one (``service.estimate.state.FilteredState``, a Kalman filter on the
reduced model, docs/design/estimator.md); the open-loop ``LiveModel`` it replaced (an FE march of a uniform
first guess with the current H, rebased after each identification) is gone.

Errors::

    LiveStateError(RuntimeError)   asked for a field before ``initialize`` / with no snapshot old enough
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from service.errors import ServiceError

__all__ = ["HeldInputs", "LiveStateError", "steady_field"]


class LiveStateError(ServiceError, RuntimeError):
    """The live state cannot answer yet (not initialised, or no snapshot that old)."""


class HeldInputs(Protocol):
    """What a steady field is computed for: H (7,) [W/(m²·K)], bearing-heat scales and the held inputs
    (ambient °C, speed rpm, torque N·m); ``service.estimate.state.FilterView`` is one."""

    @property
    def h(self) -> tuple[float, ...]: ...

    @property
    def load_scale(self) -> tuple[float, float]: ...

    @property
    def inputs(self) -> tuple[float, float, float]: ...


def steady_field(fe: Any, spec: Any, view: HeldInputs) -> np.ndarray:
    """Steady FE field (N,) °C for ``view``'s H, inputs and load scales (pure: any thread may call it)."""
    from model.fem import steady_state
    from model.inputs import inputs_from_operation

    ambient, speed, torque = view.inputs
    series = inputs_from_operation(
        spec,
        dt_s=1.0,
        speed_rpm=np.array([speed]),
        torque_nm=np.array([torque]),
        ambient_c=np.array([ambient]),
    )
    qf = float(series.q_front_w[0]) * view.load_scale[0]
    qr = float(series.q_rear_w[0]) * view.load_scale[1]
    return np.asarray(
        steady_state(fe, np.asarray(view.h, dtype=float), ambient_c=ambient, q_front_w=qf, q_rear_w=qr)
    )
