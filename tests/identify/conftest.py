"""Shared fixtures of the identification tests: the service's model (cached reduced model) and virtual-plant
data on the plant's finer mesh (never the fitted model's own output)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from model.identify import Window
from model.inputs import inputs_from_operation
from model.plant import PlantRun, Segment, VirtualPlant, h_true

TORQUE_NM = 10.0


@dataclass
class Condition:
    speed_rpm: float
    ambient_c: float
    run: PlantRun
    window: Window
    h_true: np.ndarray


@pytest.fixture(scope="session")
def model() -> Any:
    from service.modelload import ModelRef, load_model
    from service.settings import Settings

    return load_model(ModelRef.from_settings(Settings()))  # the product's model


@pytest.fixture(scope="session")
def plant(model: Any) -> VirtualPlant:
    return VirtualPlant(model.spec, noise_c=0.15, seed=11)


def make_condition(model: Any, plant: VirtualPlant, speed: float, ambient: float, *, seed: int) -> Condition:
    run = plant.run([Segment(3600.0, speed, TORQUE_NM, ambient)], dt_s=10.0, rng=np.random.default_rng(seed))
    inputs = inputs_from_operation(
        model.spec,
        dt_s=10.0,
        speed_rpm=run.speed_rpm[:-1],
        torque_nm=run.torque_nm[:-1],
        ambient_c=run.ambient_c[:-1],
    )
    window = Window(inputs, run.temps_c, np.ones(32, dtype=bool), float(run.ambient_c[0]), speed_rpm=speed)
    return Condition(speed, ambient, run, window, h_true(speed, ambient, TORQUE_NM))


@pytest.fixture(scope="session")
def cond3000(model: Any, plant: VirtualPlant) -> Condition:
    return make_condition(model, plant, 3000.0, 23.2, seed=101)


@pytest.fixture(scope="session")
def cond4000(model: Any, plant: VirtualPlant) -> Condition:
    return make_condition(model, plant, 4000.0, 21.8, seed=202)
