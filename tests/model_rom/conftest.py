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
    return build_rom(toy_fe, toy_spec, rank=30, n_train=10, n_check=6)
