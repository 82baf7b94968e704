"""Spindle geometry, materials, convective zones and sensors as data.

The description lives in a TOML file (the packaged ``model/data/spindle.toml`` by default). ``load_spindle``
parses and validates it into frozen dataclasses. Every solid part is a rectangle in the axisymmetric (r, z)
plane; the seven convective zones H1..H7 are lists of axis-aligned boundary segments.

Errors::

    SpindleError(ValueError)    a bad or missing field; the message starts with the field path,
                                e.g. ``sensors[4].r_m: must be > 0``
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from model.errors import ModelError

ZONE_NAMES = ("H1", "H2", "H3", "H4", "H5", "H6", "H7")
N_CHANNELS = 32
TEST_POINTS = (1, 3, 5, 7)
PACKAGED_SPEC = Path(__file__).parent / "data" / "spindle.toml"


class SpindleError(ModelError, ValueError):
    """A spindle description is invalid; the message names the offending field."""


@dataclass(frozen=True)
class Material:
    """Isotropic solid: conductivity k [W/(m K)], density rho [kg/m^3], specific heat c [J/(kg K)].

    Mechanical properties (optional, all three or none; only ``model.thermoelastic`` needs them): Young's
    modulus e_pa [Pa], Poisson's ratio nu [-], linear expansion coefficient alpha_per_k [1/K]. They are left
    out of ``repr`` so that the thermal model's cache key (``repr(spec)``) does not change with them.
    """

    name: str
    k_w_mk: float
    rho_kg_m3: float
    c_j_kgk: float
    e_pa: float | None = field(default=None, repr=False)
    nu: float | None = field(default=None, repr=False)
    alpha_per_k: float | None = field(default=None, repr=False)


@dataclass(frozen=True)
class Region:
    """A solid rectangle r0..r1 x z0..z1 [m]; ``heat`` marks a bearing heat source ("front"/"rear"/"")."""

    name: str
    material: str
    r0_m: float
    r1_m: float
    z0_m: float
    z1_m: float
    heat: str = ""

    def contains(self, r_m: float, z_m: float, tol: float = 1e-12) -> bool:
        """True if the point (r, z) [m] lies in the closed rectangle."""
        return (self.r0_m - tol <= r_m <= self.r1_m + tol) and (self.z0_m - tol <= z_m <= self.z1_m + tol)


@dataclass(frozen=True)
class Segment2D:
    """An axis-aligned boundary segment from (r0, z0) to (r1, z1) [m]."""

    r0_m: float
    z0_m: float
    r1_m: float
    z1_m: float


@dataclass(frozen=True)
class ZoneSpec:
    """A convective zone: its boundary segments and the data of its empirical correlation.

    ``radius_m`` sets the surface speed v = 2 pi r n / 60 of rotating zones, ``diameter_m`` the Reynolds
    length (and the cylinder diameter of stationary zones), ``length_m`` the Nusselt length l in
    H = Nu lambda / l.
    """

    name: str
    description: str
    side: Literal["ambient", "air_gap"]
    rotating: bool
    radius_m: float
    diameter_m: float
    length_m: float
    segments: tuple[Segment2D, ...]


@dataclass(frozen=True)
class SensorSpec:
    """One temperature channel at (r_m, z_m) [m], role "bearing"/"housing"/"shaft" (a pyrometer aimed at the
    shaft: docs/design/growth.md, "One shaft-side channel"), the paper's test point if any."""

    channel: int
    name: str
    r_m: float
    z_m: float
    role: Literal["bearing", "housing", "shaft"]
    test_point: int | None = None


@dataclass(frozen=True)
class BearingSpec:
    """Palmgren coefficients of one bearing set (see ``model.heat``).

    f0 [-], nu_mm2_s: lubricant kinematic viscosity [mm^2/s], dm_mm: pitch diameter [mm], f1 [-],
    p1_n: equivalent static load (preload) [N], load_per_torque_n_per_nm: extra load per N m of measured
    spindle torque [N/(N m)].
    """

    f0: float
    nu_mm2_s: float
    dm_mm: float
    f1: float
    p1_n: float
    load_per_torque_n_per_nm: float = 0.0


@dataclass(frozen=True)
class BearingSet:
    """The front and rear bearing sets."""

    front: BearingSpec
    rear: BearingSpec


@dataclass(frozen=True)
class SpindleSpec:
    """The whole spindle description (validated)."""

    name: str
    materials: Mapping[str, Material]
    regions: tuple[Region, ...]
    zones: tuple[ZoneSpec, ...]
    sensors: tuple[SensorSpec, ...]
    bearings: BearingSet
    h_box: tuple[float, float] = (5.0, 200.0)
    default_mesh_size_m: float = 0.0025
    plant_mesh_size_m: float = 0.0015
    ambient_name: str = "Ti"
    mechanics: MechanicsSpec | None = field(default=None, repr=False)

    @property
    def test_point_channels(self) -> dict[int, int]:
        """Map paper test point (1, 3, 5, 7) -> channel number (1-based)."""
        return {s.test_point: s.channel for s in self.sensors if s.test_point is not None}

    @property
    def length_m(self) -> float:
        """Axial extent of the solid [m]."""
        return max(g.z1_m for g in self.regions) - min(g.z0_m for g in self.regions)


# ---------------------------------------------------------------- field readers


def _get(d: Mapping[str, Any], key: str, path: str) -> Any:
    if key not in d:
        raise SpindleError(f"{path}{key}: missing")
    return d[key]


def _num(d: Mapping[str, Any], key: str, path: str, *, positive: bool = False, nonneg: bool = False) -> float:
    v = _get(d, key, path)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise SpindleError(f"{path}{key}: must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise SpindleError(f"{path}{key}: must be > 0, got {v!r}")
    if nonneg and v < 0:
        raise SpindleError(f"{path}{key}: must be >= 0, got {v!r}")
    return float(v)


def _str(d: Mapping[str, Any], key: str, path: str, default: str | None = None) -> str:
    if default is not None and key not in d:
        return default
    v = _get(d, key, path)
    if not isinstance(v, str):
        raise SpindleError(f"{path}{key}: must be a string, got {v!r}")
    return v


def _list(d: Mapping[str, Any], key: str, path: str) -> list[Any]:
    v = _get(d, key, path)
    if not isinstance(v, list) or not v:
        raise SpindleError(f"{path}{key}: must be a non-empty list")
    return v


def _table(d: Mapping[str, Any], key: str, path: str) -> Mapping[str, Any]:
    v = _get(d, key, path)
    if not isinstance(v, dict):
        raise SpindleError(f"{path}{key}: must be a table")
    return v


# ---------------------------------------------------------------- sections


def _materials(doc: Mapping[str, Any]) -> dict[str, Material]:
    out = {}
    for name, m in _table(doc, "materials", "").items():
        p = f"materials.{name}."
        if not isinstance(m, dict):
            raise SpindleError(f"materials.{name}: must be a table")
        k, rho, c = (_num(m, f, p, positive=True) for f in ("k_w_mk", "rho_kg_m3", "c_j_kgk"))
        out[name] = Material(name, k, rho, c, *_elastic(m, p))
    return out


def _region(d: Mapping[str, Any], path: str, materials: Mapping[str, Material]) -> Region:
    name = _str(d, "name", path)
    material = _str(d, "material", path)
    if material not in materials:
        raise SpindleError(f"{path}material: unknown material {material!r}")
    r0, r1 = _num(d, "r0_m", path, nonneg=True), _num(d, "r1_m", path, positive=True)
    z0, z1 = _num(d, "z0_m", path), _num(d, "z1_m", path)
    if r1 <= r0:
        raise SpindleError(f"{path}r1_m: must be > r0_m ({r0})")
    if z1 <= z0:
        raise SpindleError(f"{path}z1_m: must be > z0_m ({z0})")
    heat = _str(d, "heat", path, default="")
    if heat not in ("", "front", "rear"):
        raise SpindleError(f"{path}heat: must be 'front', 'rear' or '', got {heat!r}")
    return Region(name, material, r0, r1, z0, z1, heat)


def _segment(v: Any, path: str) -> Segment2D:
    try:
        (r0, z0), (r1, z1) = v
        seg = Segment2D(float(r0), float(z0), float(r1), float(z1))
    except (TypeError, ValueError) as err:
        raise SpindleError(f"{path}: must be [[r0, z0], [r1, z1]]") from err
    if (seg.r0_m != seg.r1_m) == (seg.z0_m != seg.z1_m):
        raise SpindleError(f"{path}: must be axis-aligned with non-zero length")
    if min(seg.r0_m, seg.r1_m) < 0:
        raise SpindleError(f"{path}: r must be >= 0")
    return seg


def _zone(d: Mapping[str, Any], path: str, expected: str) -> ZoneSpec:
    name = _str(d, "name", path)
    if name != expected:
        raise SpindleError(f"{path}name: expected {expected!r} (zones H1..H7 in order), got {name!r}")
    side = _str(d, "side", path)
    if side not in ("ambient", "air_gap"):
        raise SpindleError(f"{path}side: must be 'ambient' or 'air_gap', got {side!r}")
    rotating = _get(d, "rotating", path)
    if not isinstance(rotating, bool):
        raise SpindleError(f"{path}rotating: must be true or false")
    segs = tuple(_segment(s, f"{path}segments[{i}]") for i, s in enumerate(_list(d, "segments", path)))
    return ZoneSpec(
        name=name,
        description=_str(d, "description", path, default=""),
        side=side,  # type: ignore[arg-type]
        rotating=rotating,
        radius_m=_num(d, "radius_m", path, positive=True),
        diameter_m=_num(d, "diameter_m", path, positive=True),
        length_m=_num(d, "length_m", path, positive=True),
        segments=segs,
    )


def _sensor(d: Mapping[str, Any], path: str, index: int, regions: tuple[Region, ...]) -> SensorSpec:
    channel = _get(d, "channel", path)
    if channel != index + 1:
        raise SpindleError(f"{path}channel: expected {index + 1} (channels 1..32 in order), got {channel!r}")
    r, z = _num(d, "r_m", path, positive=True), _num(d, "z_m", path)
    role = _str(d, "role", path)
    if role not in ("bearing", "housing", "shaft"):
        raise SpindleError(f"{path}role: must be 'bearing', 'housing' or 'shaft', got {role!r}")
    tp = d.get("test_point")
    if tp is not None and tp not in TEST_POINTS:
        raise SpindleError(f"{path}test_point: must be one of {TEST_POINTS}, got {tp!r}")
    if not any(g.contains(r, z) for g in regions):
        raise SpindleError(f"{path}r_m: point (r={r}, z={z}) is not inside any solid region")
    return SensorSpec(index + 1, _str(d, "name", path), r, z, role, tp)  # type: ignore[arg-type]


def _bearing(d: Mapping[str, Any], path: str) -> BearingSpec:
    return BearingSpec(
        f0=_num(d, "f0", path, positive=True),
        nu_mm2_s=_num(d, "nu_mm2_s", path, positive=True),
        dm_mm=_num(d, "dm_mm", path, positive=True),
        f1=_num(d, "f1", path, nonneg=True),
        p1_n=_num(d, "p1_n", path, nonneg=True),
        load_per_torque_n_per_nm=_num(d, "load_per_torque_n_per_nm", path, nonneg=True)
        if "load_per_torque_n_per_nm" in d
        else 0.0,
    )


def _h_box(doc: Mapping[str, Any]) -> tuple[float, float]:
    box = doc.get("h_box", [5.0, 200.0])
    if not (isinstance(box, list) and len(box) == 2 and all(isinstance(b, int | float) for b in box)):
        raise SpindleError("h_box: must be [low, high]")
    lo, hi = float(box[0]), float(box[1])
    if not 0 < lo < hi:
        raise SpindleError(f"h_box: must satisfy 0 < low < high, got {box!r}")
    return lo, hi


def _unique(names: list[str], path: str) -> None:
    seen: set[str] = set()
    for i, name in enumerate(names):
        if name in seen:
            raise SpindleError(f"{path}[{i}].name: duplicate name {name!r}")
        seen.add(name)


def spec_from_dict(doc: Mapping[str, Any]) -> SpindleSpec:
    """Validate a parsed TOML document into a SpindleSpec; raise SpindleError naming the bad field."""
    materials = _materials(doc)
    regions = tuple(_region(d, f"regions[{i}].", materials) for i, d in enumerate(_list(doc, "regions", "")))
    _unique([g.name for g in regions], "regions")
    for heat in ("front", "rear"):
        if not any(g.heat == heat for g in regions):
            raise SpindleError(f"regions: no region with heat = {heat!r}")
    zones_raw = _list(doc, "zones", "")
    if len(zones_raw) != len(ZONE_NAMES):
        raise SpindleError(f"zones: expected 7 zones H1..H7, got {len(zones_raw)}")
    zones = tuple(_zone(d, f"zones[{i}].", ZONE_NAMES[i]) for i, d in enumerate(zones_raw))
    sensors_raw = _list(doc, "sensors", "")
    if len(sensors_raw) != N_CHANNELS:
        raise SpindleError(f"sensors: expected {N_CHANNELS} channels, got {len(sensors_raw)}")
    sensors = tuple(_sensor(d, f"sensors[{i}].", i, regions) for i, d in enumerate(sensors_raw))
    _unique([s.name for s in sensors], "sensors")
    tps = sorted(s.test_point for s in sensors if s.test_point is not None)
    if tps != list(TEST_POINTS):
        raise SpindleError(f"sensors: test points must be exactly {TEST_POINTS} once each, got {tps}")
    bearings = _table(doc, "bearings", "")
    mesh = doc.get("mesh", {})
    amb = doc.get("ambient", {})
    return SpindleSpec(
        name=_str(doc, "name", "", default="spindle"),
        materials=materials,
        regions=regions,
        zones=zones,
        sensors=sensors,
        bearings=BearingSet(
            front=_bearing(_table(bearings, "front", "bearings."), "bearings.front."),
            rear=_bearing(_table(bearings, "rear", "bearings."), "bearings.rear."),
        ),
        h_box=_h_box(doc),
        default_mesh_size_m=_num(mesh, "default_size_m", "mesh.", positive=True)
        if "default_size_m" in mesh
        else 0.0025,
        plant_mesh_size_m=_num(mesh, "plant_size_m", "mesh.", positive=True)
        if "plant_size_m" in mesh
        else 0.0015,
        ambient_name=_str(amb, "name", "ambient.", default="Ti"),
        mechanics=_mechanics(doc["mechanics"], regions, materials) if "mechanics" in doc else None,
    )


def load_spindle(path: str | Path | None = None) -> SpindleSpec:
    """Load and validate a spindle TOML file; None loads the packaged ``model/data/spindle.toml``."""
    p = PACKAGED_SPEC if path is None else Path(path)
    try:
        with p.open("rb") as fh:
            doc = tomllib.load(fh)
    except OSError as err:
        raise SpindleError(f"{p}: cannot read ({err.strerror})") from err
    except tomllib.TOMLDecodeError as err:
        raise SpindleError(f"{p}: invalid TOML ({err})") from err
    return spec_from_dict(doc)


# ---------------------------------------------------------------- mechanics (thermoelastic model, optional)

MOUNT_FIXES = ("axial", "axial_radial")
SURFACES = ("outer", "inner")
COMPONENTS = ("axial", "radial")


@dataclass(frozen=True)
class MountSpec:
    """The housing's mounting face: segments on the solid's boundary, held axially (and radially if asked)."""

    segments: tuple[Segment2D, ...]
    fix: Literal["axial", "axial_radial"] = "axial"
    description: str = ""


@dataclass(frozen=True)
class FloatingSpec:
    """A region whose ``surface`` ("outer": r = r1, "inner": r = r0) slides axially (floating bearing)."""

    region: str
    surface: Literal["outer", "inner"] = "outer"


@dataclass(frozen=True)
class GrowthOutputSpec:
    """A displacement output: the ``component`` ("axial" u_z / "radial" u_r) at the point (r_m, z_m) [m]."""

    name: str
    component: Literal["axial", "radial"]
    r_m: float
    z_m: float
    description: str = ""


@dataclass(frozen=True)
class MechanicsSpec:
    """Boundary conditions and outputs of the thermoelastic model (``[mechanics]`` in the TOML).

    ``region_material`` overrides a region's material for the mechanics only (region name -> material).
    """

    mount: MountSpec
    floating: tuple[FloatingSpec, ...]
    outputs: tuple[GrowthOutputSpec, ...]
    region_material: Mapping[str, str] = field(default_factory=dict)


def _elastic(m: Mapping[str, Any], p: str) -> tuple[float | None, float | None, float | None]:
    keys = ("e_pa", "nu", "alpha_per_k")
    present = [k for k in keys if k in m]
    if not present:
        return None, None, None
    for k in keys:
        _get(m, k, p)  # all three or none
    nu, alpha = _num(m, "nu", p), _num(m, "alpha_per_k", p)
    if not 0.0 <= nu < 0.5:
        raise SpindleError(f"{p}nu: must be in [0, 0.5), got {nu!r}")
    if not abs(alpha) < 1e-3:
        raise SpindleError(f"{p}alpha_per_k: must be in 1/K with |alpha| < 1e-3 (11.5 um/(m K) = 1.15e-5)")
    return _num(m, "e_pa", p, positive=True), nu, alpha


def _choice(d: Mapping[str, Any], key: str, path: str, options: tuple[str, ...], default: str) -> str:
    v = _str(d, key, path, default=default)
    if v not in options:
        raise SpindleError(f"{path}{key}: must be one of {options}, got {v!r}")
    return v


def _mount(d: Mapping[str, Any]) -> MountSpec:
    p = "mechanics.mount."
    segs = tuple(_segment(s, f"{p}segments[{i}]") for i, s in enumerate(_list(d, "segments", p)))
    fix = _choice(d, "fix", p, MOUNT_FIXES, "axial")
    return MountSpec(segs, fix, _str(d, "description", p, default=""))  # type: ignore[arg-type]


def _floating(d: Any, p: str, regions: tuple[Region, ...]) -> FloatingSpec:
    if not isinstance(d, dict):
        raise SpindleError(f"{p[:-1]}: must be a table")
    name = _str(d, "region", p)
    match = [g for g in regions if g.name == name]
    if not match:
        raise SpindleError(f"{p}region: unknown region {name!r}")
    surface = _choice(d, "surface", p, SURFACES, "outer")
    if surface == "inner" and match[0].r0_m == 0.0:
        raise SpindleError(f"{p}surface: region {name!r} has no inner surface (r0_m = 0)")
    return FloatingSpec(name, surface)  # type: ignore[arg-type]


def _output(d: Any, p: str, regions: tuple[Region, ...]) -> GrowthOutputSpec:
    if not isinstance(d, dict):
        raise SpindleError(f"{p[:-1]}: must be a table")
    r, z = _num(d, "r_m", p, nonneg=True), _num(d, "z_m", p)
    if not any(g.contains(r, z) for g in regions):
        raise SpindleError(f"{p}r_m: point (r={r}, z={z}) is not inside any solid region")
    comp = _choice(d, "component", p, COMPONENTS, "axial")
    return GrowthOutputSpec(_str(d, "name", p), comp, r, z, _str(d, "description", p, default=""))  # type: ignore[arg-type]


def _region_material(
    d: Mapping[str, Any], regions: tuple[Region, ...], materials: Mapping[str, Material]
) -> dict[str, str]:
    names = {g.name for g in regions}
    out = {}
    for region, material in d.items():
        if region not in names:
            raise SpindleError(f"mechanics.region_material.{region}: unknown region")
        if not isinstance(material, str) or material not in materials:
            raise SpindleError(f"mechanics.region_material.{region}: unknown material {material!r}")
        out[region] = material
    return out


def _check_elastic(
    regions: tuple[Region, ...], override: Mapping[str, str], materials: Mapping[str, Material]
) -> None:
    for g in regions:
        name = override.get(g.name, g.material)
        if materials[name].e_pa is None:
            raise SpindleError(f"materials.{name}.e_pa: missing (region {g.name!r} needs E, nu, alpha_per_k)")


def _mechanics(doc: Any, regions: tuple[Region, ...], materials: Mapping[str, Material]) -> MechanicsSpec:
    if not isinstance(doc, dict):
        raise SpindleError("mechanics: must be a table")
    floating_raw = doc.get("floating", [])
    if not isinstance(floating_raw, list):
        raise SpindleError("mechanics.floating: must be a list of tables")
    floating = tuple(_floating(d, f"mechanics.floating[{i}].", regions) for i, d in enumerate(floating_raw))
    outs = _list(doc, "outputs", "mechanics.")
    outputs = tuple(_output(d, f"mechanics.outputs[{i}].", regions) for i, d in enumerate(outs))
    _unique([o.name for o in outputs], "mechanics.outputs")
    rm = doc.get("region_material", {})
    if not isinstance(rm, dict):
        raise SpindleError("mechanics.region_material: must be a table")
    override = _region_material(rm, regions, materials)
    _check_elastic(regions, override, materials)
    return MechanicsSpec(
        mount=_mount(_table(doc, "mount", "mechanics.")),
        floating=floating,
        outputs=outputs,
        region_material=override,
    )
