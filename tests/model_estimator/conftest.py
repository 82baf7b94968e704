"""Fixtures of the estimator tests: the service's reduced model (cached, rank 30) and one virtual-plant run
on the plant's finer mesh with its own truth (never the filter's own model output)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from model.estimator import StepInput
from model.inputs import InputSeries, inputs_from_operation
from model.plant import PlantRun, Segment, VirtualPlant

# the restart profile, shortened: 5 min idle, 3000 rpm 60 min, 4000 rpm 45 min (10 N·m, 22 °C)
PROFILE = (
    Segment(300.0, 0.0, 0.0, 22.0),
    Segment(3600.0, 3000.0, 10.0, 22.0),
    Segment(2700.0, 4000.0, 10.0, 22.0),
)


@dataclass
class PlantData:
    run: PlantRun
    inputs: InputSeries
    final_field_c: np.ndarray  # plant's last field interpolated onto the service mesh (N,) [°C]

    def step_input(self, k: int, h_factor: np.ndarray | None = None) -> StepInput:
        """Inputs of step k -> k+1 with the plant's true H (times ``h_factor``)."""
        h = self.run.h_true[k] * (1.0 if h_factor is None else h_factor)
        inp = self.inputs
        return StepInput(h, float(inp.ambient_c[k]), float(inp.q_front_w[k]), float(inp.q_rear_w[k]))


@pytest.fixture(scope="session")
def model() -> Any:
    from service.modelload import ModelRef, load_model
    from service.settings import default_cache_dir

    return load_model(ModelRef(cache_dir=str(default_cache_dir())))


@pytest.fixture(scope="session")
def plant_data(model: Any) -> PlantData:
    from scipy.interpolate import LinearNDInterpolator

    # steady_tol_c=0: no "converged, fill the rest of the segment" shortcut, whose frozen truth is not the
    # slow drift a real spindle shows (the filter would be judged against an artefact)
    plant = VirtualPlant(model.spec, noise_c=0.15, seed=11, steady_tol_c=0.0)
    run = plant.run(list(PROFILE), dt_s=10.0, rng=np.random.default_rng(2026))
    inputs = inputs_from_operation(
        model.spec,
        dt_s=10.0,
        speed_rpm=run.speed_rpm[:-1],
        torque_nm=run.torque_nm[:-1],
        ambient_c=run.ambient_c[:-1],
    )
    final = LinearNDInterpolator(plant.fe.nodes_rz, run.final_field_c)(model.fe.nodes_rz)
    assert np.all(np.isfinite(final))
    return PlantData(run, inputs, np.asarray(final))
