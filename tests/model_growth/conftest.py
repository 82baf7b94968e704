"""Fixtures: the packaged spindle, its FE model at the default mesh and the growth model (built once)."""

from __future__ import annotations

import copy
import tomllib
from typing import Any

import pytest

from model.fem import FEModel, build_fe_model
from model.geometry import PACKAGED_SPEC, SpindleSpec, load_spindle
from model.thermoelastic import GrowthModel, build_growth_model

H_TABLE4 = (88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54)


def packaged_doc() -> dict[str, Any]:
    """A fresh, editable copy of the packaged spindle TOML."""
    with PACKAGED_SPEC.open("rb") as fh:
        return copy.deepcopy(tomllib.load(fh))


@pytest.fixture(scope="session")
def spec() -> SpindleSpec:
    return load_spindle()


@pytest.fixture(scope="session")
def fe(spec: SpindleSpec) -> FEModel:
    return build_fe_model(spec)


@pytest.fixture(scope="session")
def growth(spec: SpindleSpec, fe: FEModel) -> GrowthModel:
    return build_growth_model(spec, fe)
