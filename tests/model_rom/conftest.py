"""Fixtures of the reduced-model tests: a small stand-in affine system and a reduced model of it; the real
spindle's FE model on a coarse mesh and its reduced model (built once per session, shared by
``test_rom_spindle`` and ``test_rom_split``)."""

from __future__ import annotations

import pytest

from model.fem import FEModel, build_fe_model
from model.geometry import SpindleSpec, load_spindle
from model.rom import ReducedModel, build_rom, load_or_build_rom

from ._toy import ToyFE, ToySpec, build_toy


@pytest.fixture(scope="session")
def toy_fe() -> ToyFE:
    return build_toy(refine=2)


@pytest.fixture(scope="session")
def toy_spec() -> ToySpec:
    return ToySpec()


@pytest.fixture(scope="session")
def toy_rom(toy_fe: ToyFE, toy_spec: ToySpec) -> ReducedModel:
    # substeps=1: these tests check the closed form against plain θ-method stepping of the same Δt
    return build_rom(toy_fe, toy_spec, rank=30, n_train=10, n_check=6, substeps=1)


@pytest.fixture(scope="session")
def spindle_spec() -> SpindleSpec:
    return load_spindle()


@pytest.fixture(scope="session")
def coarse_fe(spindle_spec: SpindleSpec) -> FEModel:
    """The packaged spindle on a coarse mesh (8 mm) to stay fast."""
    return build_fe_model(spindle_spec, mesh_size_m=0.008)


@pytest.fixture(scope="session")
def coarse_rom(
    coarse_fe: FEModel, spindle_spec: SpindleSpec, tmp_path_factory: pytest.TempPathFactory
) -> ReducedModel:
    """Its reduced model at the default options, fewer training and check draws (built here, not cached)."""
    return load_or_build_rom(coarse_fe, spindle_spec, tmp_path_factory.mktemp("rom"), n_train=10, n_check=4)
