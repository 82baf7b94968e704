"""Fixtures of the H-map tests: the service's model (cached reduced model) and a duty cycle on the virtual
plant (finer mesh, its own h_true: never the fitted model's own output)."""

from __future__ import annotations

from typing import Any

import pytest

from model.plant import VirtualPlant
from tests.model_hmap.duty import DutyRun, load_service_model, run_duty


@pytest.fixture(scope="session")
def model() -> Any:
    return load_service_model()


@pytest.fixture(scope="session")
def duty(model: Any) -> DutyRun:
    """A seeded 2-h duty cycle (speed changes every 1-6 min among 0..7000 rpm, torque 3-15 N·m, ambient
    drifting ±1 °C) sampled every 10 s."""
    return run_duty(VirtualPlant(model.spec, seed=5), 5, duration_s=7200.0)
