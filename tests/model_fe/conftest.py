"""Fixtures for the FE model tests: the packaged spindle and a coarse FE model of it (built once)."""

from __future__ import annotations

import pytest

from model.fem import FEModel, build_fe_model
from model.geometry import SpindleSpec, load_spindle


@pytest.fixture(scope="session")
def spec() -> SpindleSpec:
    return load_spindle()


@pytest.fixture(scope="session")
def coarse_fe(spec: SpindleSpec) -> FEModel:
    return build_fe_model(spec, mesh_size_m=0.005)
