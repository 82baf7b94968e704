"""Fixtures of the estimator tests: the service's reduced model (cached, default settings) and one
virtual-plant run on the plant's finer mesh with its own truth (never the filter's own model output)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from model.estimator import StepInput
from model.fem import build_fe_model
from model.geometry import load_spindle
from model.inputs import InputSeries, inputs_from_operation
from model.plant import PlantRun, Segment, VirtualPlant
from model.rom import DEFAULT_RANK, load_or_build_rom

SERVICE_RANK = DEFAULT_RANK  # the service settings' experimental.rom_rank default follows it (46 today)

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


@dataclass(frozen=True)
class Model:
    spec: Any
    fe: Any
    rom: Any


def _cache_dir() -> Path:
    """The service's reduced-model cache (same rule as ``service.settings.default_cache_dir``), so the
    model is built once per machine and shared with the service and the other tests."""
    if env := os.environ.get("CHTC_CACHE_DIR"):
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "spindle-chtc"


@pytest.fixture(scope="session")
def model() -> Model:
    """The service's model from ``model/`` alone: packaged spindle, default mesh, reduced model at the
    default rank and box with the default step (exact over each held 10-s step, ``rom.substeps`` 0): the
    service settings' defaults (~15–40 s to build on a cache miss)."""
    spec = load_spindle()
    fe = build_fe_model(spec)
    cache = _cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    rom = load_or_build_rom(fe, spec, cache, rank=SERVICE_RANK, box=(5.0, 200.0))
    return Model(spec, fe, rom)


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
