"""A virtual plant's own mechanics, drawn per seed (pure): what the service's ``[mechanics]`` does not know.

The service builds its growth model from the spindle description as written (``fix = "axial"``, the
materials' α). A real machine differs; the plant draws (docs/design/growth.md, "A plant with its own
mechanics")::

    restraint s ~ U(0, 1)            the mounting flange's radial restraint: a radial Winkler spring on the
                                     mounting face, k = K_HALF · s / (1 − s) [N/m per m² of face];
                                     s = 0 free (``fix = "axial"``), s = 1 held (``"axial_radial"``)
    alpha_shaft   ~ U(0.95, 1.05)    factor on α of the shaft's material (all regions made of it)
    alpha_housing ~ U(0.95, 1.05)    factor on α of the housing's material (housing and end caps)

Why a spring and this mapping: the FE mechanics take a stiffness on the u_r dofs of the face directly
(``model.thermoelastic.mount_spring``); measured on the plant mesh at steady 5000 rpm, every output moves from
its free to its held value as k / (k + k_c) with k_c ≈ 1·10¹² Pa/m (nose axial 0.091 / 0.508 / 0.928 of the
way at k = 10¹¹ / 10¹² / 10¹³; the other outputs within 0.03 of it). With K_HALF = k_c the growth is then
nearly linear in s, so s reads as "the fraction of the way from free to held" and a commissioning fit can
treat the growth as linear in it. 10¹² Pa/m over the 0.0113 m² face (r 80–100 mm) is a total radial
stiffness of ≈ 11 kN/µm: a bolted flange held by friction on a stiff spindle head.

Not drawn, because it does not matter (measured on the plant mesh, steady 5000 rpm, nose axial 8.18 µm):
a floating bearing that sticks (friction without limit: fused) moves it by +0.05 µm; the lumped bearings'
stiffness (preload) halved or doubled by −0.05 / +0.08 µm; both far below the restraint (10.9 µm between
free and held) and α's ±5 % (±0.4 µm).

The α groups and their scatter (``alpha_region_scales``, ``ALPHA_REL``) are the product's
(``model.mechprior``): the commissioning fit knows the same ranges the plant draws from.

Errors::

    PlantMechanicsError(ValueError)   a value outside its range
    model.mechprior.MechanicsSpecError(ValueError)   a spindle without [mechanics] or without the
                                                     shaft/housing regions
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from model.errors import ModelError
from model.fem import FEModel
from model.geometry import SpindleSpec
from model.mechprior import ALPHA_REL, alpha_region_scales, mount_fix
from model.thermoelastic import GrowthModel, MechanicsVariant, build_growth_model

__all__ = [
    "ALPHA_REL",
    "K_HALF_PA_PER_M",
    "PlantMechanics",
    "PlantMechanicsError",
    "alpha_region_scales",
    "build_plant_growth",
    "mechanics_for_seed",
]

K_HALF_PA_PER_M = 1.0e12  # radial face stiffness at which the growth is half-way from free to held
SEED_STREAM = 11  # the mechanics' own stream: rng([seed, 11]); the truth uses [seed, 7]


class PlantMechanicsError(ModelError, ValueError):
    """Bad plant mechanics; the message names the field."""


@dataclass(frozen=True)
class PlantMechanics:
    """One plant's mechanics: ``restraint`` s in [0, 1] (0 free, 1 held radially), α factors [-]."""

    restraint: float = 0.0
    alpha_shaft: float = 1.0
    alpha_housing: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.restraint <= 1.0:
            raise PlantMechanicsError(f"restraint: must be in [0, 1], got {self.restraint!r}")
        for name in ("alpha_shaft", "alpha_housing"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.5 < value < 1.5):
                raise PlantMechanicsError(f"{name}: must be a factor in (0.5, 1.5), got {value!r}")

    @classmethod
    def nominal(cls, spec: SpindleSpec) -> PlantMechanics:
        """The description's own mechanics: its mount fixing, α as written (what the service assumes)."""
        fix = mount_fix(spec)
        return cls(restraint=0.0 if fix == "axial" else 1.0)

    @classmethod
    def draw(cls, rng: np.random.Generator) -> PlantMechanics:
        """Mechanics drawn with ``rng`` (module docstring): s ~ U(0, 1), each α factor ~ U(1 ± 0.05)."""
        s = float(rng.uniform(0.0, 1.0))
        a_s, a_h = (float(a) for a in rng.uniform(1.0 - ALPHA_REL, 1.0 + ALPHA_REL, 2))
        return cls(restraint=s, alpha_shaft=a_s, alpha_housing=a_h)

    @property
    def spring_pa_per_m(self) -> float:
        """The mounting face's radial spring [N/m per m²]: K_HALF · s / (1 − s); inf when held (s = 1)."""
        if self.restraint >= 1.0:
            return math.inf
        return K_HALF_PA_PER_M * self.restraint / (1.0 - self.restraint)

    def variant(self, spec: SpindleSpec) -> MechanicsVariant:
        """What ``model.thermoelastic.build_growth_model`` changes for these mechanics on ``spec``."""
        mount_fix(spec)
        scales = alpha_region_scales(spec, self.alpha_shaft, self.alpha_housing)
        if self.restraint >= 1.0:
            return MechanicsVariant(fix="axial_radial", region_alpha_scale=scales)
        return MechanicsVariant(
            fix="axial", mount_spring_pa_per_m=self.spring_pa_per_m, region_alpha_scale=scales
        )

    def as_dict(self) -> dict[str, float]:
        """JSON-ready: the draw and the spring it means."""
        return {
            "restraint": round(self.restraint, 4),
            "spring_pa_per_m": self.spring_pa_per_m,
            "alpha_shaft": round(self.alpha_shaft, 4),
            "alpha_housing": round(self.alpha_housing, 4),
        }


def mechanics_for_seed(seed: int) -> PlantMechanics:
    """The plant mechanics of bench seed ``seed``: ``PlantMechanics.draw(default_rng([seed, 11]))`` (its own
    stream: the seed's truth and duty cycle are the same with or without drawn mechanics)."""
    return PlantMechanics.draw(np.random.default_rng([int(seed), SEED_STREAM]))


def build_plant_growth(spec: SpindleSpec, fe: FEModel, mechanics: PlantMechanics) -> GrowthModel:
    """The plant's growth model with its own ``mechanics`` on its own mesh ``fe`` (~0.7 s, 1.5-mm mesh)."""
    return build_growth_model(spec, fe, variant=mechanics.variant(spec))
