"""The mechanics a spindle description leaves open, as the growth fit and the served growth see them (pure).

A description's ``[mechanics]`` fixes the mount (``fix``) and names the materials' α; a real machine
differs in the mount's radial restraint and in α between heats of the same material. The commissioning fit
(``model.growthfit``) and the served growth's mechanics (``service.estimate.mechanics``) treat α as two
factors, one on every region of the shaft's material and one on every region of the housing's material
(``alpha_region_scales``), each known to ``ALPHA_REL`` before a test. The virtual plant draws its own
mechanics within the same ranges (``model.plantmech``).

Errors::

    MechanicsSpecError(ValueError)   a spindle without [mechanics] or without the shaft/housing regions
"""

from __future__ import annotations

from model.errors import ModelError
from model.geometry import SpindleSpec

__all__ = [
    "ALPHA_REL",
    "HOUSING_REGION",
    "SHAFT_PREFIX",
    "MechanicsSpecError",
    "alpha_region_scales",
    "mount_fix",
]

ALPHA_REL = 0.05  # α scatter between heats of the same material: ±5 %
SHAFT_PREFIX = "shaft"  # regions named shaft* give the shaft's material
HOUSING_REGION = "housing"  # this region gives the housing's material


class MechanicsSpecError(ModelError, ValueError):
    """A spindle description the mechanics' parameters cannot apply to; the message names the field."""


def mount_fix(spec: SpindleSpec) -> str:
    """The description's mount fixing (``axial`` or ``axial_radial``); raises without ``[mechanics]``."""
    if spec.mechanics is None:
        raise MechanicsSpecError("spec.mechanics: the spindle description has no [mechanics] section")
    return spec.mechanics.mount.fix


def _effective_material(spec: SpindleSpec, region: str) -> str:
    assert spec.mechanics is not None
    mat = next(g.material for g in spec.regions if g.name == region)
    return spec.mechanics.region_material.get(region, mat)


def alpha_region_scales(spec: SpindleSpec, alpha_shaft: float, alpha_housing: float) -> tuple[float, ...]:
    """Per region (``spec.regions`` order): the shaft's factor on every region of the shaft's material, the
    housing's on every region of the housing's material, 1 elsewhere (bearings, pulley)."""
    mount_fix(spec)
    names = [g.name for g in spec.regions]
    shaft = {_effective_material(spec, n) for n in names if n.startswith(SHAFT_PREFIX)}
    if len(shaft) != 1 or HOUSING_REGION not in names:
        raise MechanicsSpecError(
            f"spec.regions: need regions named {SHAFT_PREFIX}* of one material "
            f"and a {HOUSING_REGION!r} region"
        )
    shaft_mat, housing_mat = shaft.pop(), _effective_material(spec, HOUSING_REGION)
    if shaft_mat == housing_mat:
        raise MechanicsSpecError("spec.regions: shaft and housing share a material; their α cannot differ")
    out = []
    for n in names:
        mat = _effective_material(spec, n)
        out.append(alpha_shaft if mat == shaft_mat else alpha_housing if mat == housing_mat else 1.0)
    return tuple(out)
