"""The reduced model's one-step error against the full FE, as process noise for ``model.estimator``.

The full FE field T_k (``model.fem.simulate``) is projected onto the reduced basis, a_k = Vᵀ·E·T_k, and
stepped once with the reduced model: the defect w_k = a_{k+1} − (A·a_k + G·z_r,k) is what the reduced step
misses when it starts from the true state (Galerkin error of the step, boundary layers outside the basis).
Its second moment over a few histories is the model part of Q. The field's part outside the basis shows at
the sensors as C_fe·T_k − C·a_k; its RMS is reported as a candidate for ``NoiseModel.sigma_model_c``.

Errors: ``model.estimator.EstimatorError`` for an empty case list.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from model.estimator import EstimatorError, StepInput, predict_mean, transition
from model.fem import simulate
from model.inputs import InputSeries, inputs_from_operation

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DefectCase:
    """One full-FE history: H (7,) [W/(m²·K)], inputs and the start (uniform °C or (N,) field)."""

    h: Array
    inputs: InputSeries
    t0: float | Array


@dataclass(frozen=True, eq=False)
class DefectReport:
    """``cov`` (r, r) [°C² per step, reduced]; ``sensor_rms_c`` the RMS of the step defect at the sensors,
    C·w; ``outside_rms_c`` the RMS at the sensors of the field outside the basis; ``steps`` counted."""

    cov: Array
    sensor_rms_c: float
    outside_rms_c: float
    steps: int


def standard_cases(
    spec: Any, *, seed: int = 0, n_h: int = 3, box: tuple[float, float] = (5.0, 200.0)
) -> list[DefectCase]:
    """``n_h`` log-uniform random H in ``box``, each with the same 60-min history: 5 min idle, 25 min at
    3000 rpm and 30 min at 5000 rpm (10 N·m), ambient drifting 22 → 23 °C, 10-s steps, cold start."""
    rng = np.random.default_rng(seed)
    n = 360
    speed = np.where(np.arange(n) < 30, 0.0, np.where(np.arange(n) < 180, 3000.0, 5000.0))
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=speed, torque_nm=10.0, ambient_c=np.linspace(22.0, 23.0, n)
    )
    lo, hi = np.log(box[0]), np.log(box[1])
    return [DefectCase(np.exp(rng.uniform(lo, hi, 7)), inputs, 22.0) for _ in range(n_h)]


def rom_defect_cov(rom: Any, fe: Any, cases: Sequence[DefectCase]) -> DefectReport:
    """The reduced model's one-step defect vs the full FE over ``cases`` (about 0.3 s of FE per hour of
    10-s steps on the default mesh)."""
    if not cases:
        raise EstimatorError("cases: need at least one full-FE history")
    defects, outside = [], []
    for case in cases:
        fields = simulate(fe, case.h, case.inputs, case.t0)
        a = rom.project(fields)  # (n+1, r)
        tr = transition(rom, case.h, case.inputs.dt_s)
        inp = case.inputs
        for k in range(inp.n_steps):
            u = StepInput(case.h, float(inp.ambient_c[k]), float(inp.q_front_w[k]), float(inp.q_rear_w[k]))
            defects.append(a[k + 1] - predict_mean(tr, a[k], u))
        outside.append(np.asarray(fe.sensors(fields)) - a @ np.asarray(rom.sensors).T)
    w = np.asarray(defects)
    cov = w.T @ w / len(w)
    sens = w @ np.asarray(rom.sensors).T
    out = np.concatenate(outside)
    return DefectReport(
        0.5 * (cov + cov.T), float(np.sqrt(np.mean(sens**2))), float(np.sqrt(np.mean(out**2))), len(w)
    )
