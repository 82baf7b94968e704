"""Fixtures of the reduced-model tests: a small stand-in affine system and a reduced model of it."""

from __future__ import annotations

import pytest

from model.rom import ReducedModel, build_rom

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
