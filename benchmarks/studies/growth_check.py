"""Studies of the thermoelastic growth model for docs/design/growth.md: mesh convergence, the 1-D rule beside
the 2-D result, the cost of the modelling choices, sensor sensitivity and the cost of one evaluation.

The functions are pure (they return rows); ``python -m benchmarks.studies.growth_check`` prints them
(``--json``). Realistic fields are steady states of ``model.fem`` at the paper's Table 4 H, ambient 20 °C,
T_ref 20 °C.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from benchmarks.studies.growth_path import Band, axial_1d_um
from model.fem import FEModel, build_fe_model, simulate, steady_state
from model.geometry import PACKAGED_SPEC, SpindleSpec, load_spindle, spec_from_dict
from model.growth import reconstruction_h_fit, sensor_sensitivity, steady_jacobian_h
from model.heat import bearing_heat_w
from model.inputs import InputSeries
from model.thermoelastic import GrowthModel, build_growth_model

H_TABLE4 = (88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54)
AMBIENT_C = 20.0
Array = NDArray[np.float64]


def steady_field(spec: SpindleSpec, fe: FEModel, speed_rpm: float, torque_nm: float = 0.0) -> Array:
    """Steady field (N,) [°C] at Table 4 H, ambient 20 °C, Palmgren heats for the speed and torque."""
    qf = float(bearing_heat_w(speed_rpm, torque_nm, spec.bearings.front))
    qr = float(bearing_heat_w(speed_rpm, torque_nm, spec.bearings.rear))
    return steady_state(fe, H_TABLE4, ambient_c=AMBIENT_C, q_front_w=qf, q_rear_w=qr)


@dataclass(frozen=True)
class MeshRow:
    """One mesh: size [m], thermal nodes, build time of the growth model [s], outputs [µm], rel. error."""

    mesh_size_m: float
    n_nodes: int
    build_s: float
    growth_um: dict[str, float]
    rel_err: dict[str, float]


def _outputs(spec: SpindleSpec, size: float, speed_rpm: float) -> tuple[int, float, dict[str, float]]:
    fe = build_fe_model(spec, mesh_size_m=size)
    started = time.perf_counter()
    gm = build_growth_model(spec, fe)
    build_s = time.perf_counter() - started
    return fe.n_nodes, build_s, gm.as_dict(gm.growth_um(steady_field(spec, fe, speed_rpm), AMBIENT_C))


def mesh_study(
    spec: SpindleSpec, *, sizes_m: Sequence[float], reference_m: float, speed_rpm: float = 5000.0
) -> list[MeshRow]:
    """Outputs at each mesh size against a finer reference; each mesh solves its own steady field."""
    _, _, ref = _outputs(spec, reference_m, speed_rpm)
    rows = []
    for size in sizes_m:
        n, build_s, got = _outputs(spec, size, speed_rpm)
        err = {k: (got[k] - ref[k]) / ref[k] for k in ref}
        rows.append(MeshRow(float(size), n, build_s, got, err))
    return rows


def path_bands(z_loc: float, *, line: bool = False) -> tuple[Band, Band]:
    """Housing wall (r 65-100 mm) from z_loc to the mount, shaft (r 0-40 mm) from z_loc to the nose.

    ``line`` takes one line instead of the section mean: r = 82.5 mm in the housing, the axis in the shaft.
    """
    if line:
        return Band(0.0825, 0.0825, z_loc, 0.550), Band(0.0, 0.0, z_loc, 0.610)
    return Band(0.065, 0.100, z_loc, 0.550), Band(0.0, 0.040, z_loc, 0.610)


ONE_D_RULES: dict[str, tuple[float, bool, bool]] = {
    # name: (locating plane z [m], one line instead of the section mean, ignore the housing)
    "1-D, locating plane at bearing A centre": (0.4875, False, False),
    "1-D, locating plane at the pair centre": (0.505, False, False),
    "1-D, locating plane at bearing B centre": (0.5225, False, False),
    "1-D, pair centre, axis / one housing line": (0.505, True, False),
    "1-D, pair centre, shaft only (housing ignored)": (0.505, False, True),
}


def _heats(spec: SpindleSpec, speed_rpm: float, torque_nm: float = 0.0) -> tuple[float, float]:
    return (
        float(bearing_heat_w(speed_rpm, torque_nm, spec.bearings.front)),
        float(bearing_heat_w(speed_rpm, torque_nm, spec.bearings.rear)),
    )


def _run(fe: FEModel, start: Array | float, heats: tuple[float, float], minutes: int) -> Array:
    n = 6 * minutes
    inputs = InputSeries(
        dt_s=10.0,
        ambient_c=np.full(n, AMBIENT_C),
        q_front_w=np.full(n, heats[0]),
        q_rear_w=np.full(n, heats[1]),
    )
    return np.asarray(simulate(fe, H_TABLE4, inputs, start)[-1])


def realistic_fields(spec: SpindleSpec, fe: FEModel) -> dict[str, Array]:
    """Fields (N,) [°C] of different shape: heating transients, steady states, a cool-down (Table 4 H)."""
    hot = steady_field(spec, fe, 7000.0)
    return {
        "5000 rpm, 10 min from cold": _run(fe, AMBIENT_C, _heats(spec, 5000.0), 10),
        "5000 rpm, 30 min from cold": _run(fe, AMBIENT_C, _heats(spec, 5000.0), 30),
        "5000 rpm, steady": steady_field(spec, fe, 5000.0),
        "3000 rpm 20 N m, steady": steady_field(spec, fe, 3000.0, 20.0),
        "stop after steady 7000 rpm, +20 min": _run(fe, hot, (0.0, 0.0), 20),
    }


def one_d_table(
    spec: SpindleSpec, fe: FEModel, gm: GrowthModel, fields: dict[str, Array]
) -> list[dict[str, Any]]:
    """Nose axial growth [µm]: the 2-D model and the 1-D rules, per field."""
    rows = []
    for label, field in fields.items():
        rise = field - AMBIENT_C
        row: dict[str, Any] = {"field": label, "max_rise_c": float(rise.max())}
        row["2-D model"] = float(gm.operator("nose_axial") @ rise)
        for name, (z_loc, line, shaft_only) in ONE_D_RULES.items():
            housing, shaft = path_bands(z_loc, line=line)
            if shaft_only:
                housing = Band(0.065, 0.100, 0.550, 0.550 + 1e-9)
            row[name] = axial_1d_um(spec, fe, rise, housing=housing, shaft=shaft)
        rows.append(row)
    return rows


def _doc() -> dict[str, Any]:
    with PACKAGED_SPEC.open("rb") as fh:
        return copy.deepcopy(tomllib.load(fh))


def variants() -> dict[str, dict[str, Any]]:
    """Modelling choices to compare: name -> edited spindle document."""
    out = {"packaged": _doc()}
    stiff = _doc()
    stiff["materials"]["bearing"]["e_pa"] = 2.1e11
    out["bearing solid as steel (E 210 GPa)"] = stiff
    fused = _doc()
    fused["mechanics"]["floating"] = []
    out["rear bearing fused (not floating)"] = fused
    clamped = _doc()
    clamped["mechanics"]["mount"]["fix"] = "axial_radial"
    out["mount held radially too"] = clamped
    spacer = _doc()
    spacer["mechanics"]["region_material"] = {}
    out["spacer as solid steel (stiff shaft-housing tie)"] = spacer
    return out


def variant_table(fe: FEModel, speed_rpm: float = 5000.0) -> list[dict[str, Any]]:
    """Outputs [µm] of each modelling variant for the same steady field (the thermal model is unchanged)."""
    rows = []
    for name, doc in variants().items():
        spec = spec_from_dict(doc)
        gm = build_growth_model(spec, fe)
        rise = steady_field(spec, fe, speed_rpm) - AMBIENT_C
        rows.append({"variant": name, **gm.as_dict(gm.growth_um(rise, 0.0))})
    return rows


def eval_cost_us(gm: GrowthModel, *, repeats: int = 2000, rank: int = 46) -> dict[str, float]:
    """Median wall time [µs] of one evaluation: all outputs from a nodal field, and from a reduced state."""
    rng = np.random.default_rng(0)
    field = 20.0 + rng.normal(size=gm.n_nodes)
    gphi = gm.reduced(rng.normal(size=(gm.n_nodes, rank)))
    a = rng.normal(size=rank)

    def median_us(fn: Any) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return float(np.median(times) * 1e6)

    return {
        "nodal_us": median_us(lambda: gm.growth_um(field, 20.0)),
        "reduced_us": median_us(lambda: gphi @ a),
        "n_nodes": float(gm.n_nodes),
        "n_outputs": float(len(gm.names)),
        "rank": float(rank),
    }


def sensitivity_table(
    spec: SpindleSpec,
    fe: FEModel,
    gm: GrowthModel,
    speed_rpm: float = 5000.0,
    *,
    prior_rel: float | None = None,
    noise_c: float = 0.15,
) -> Array:
    """(n_out, 32) [µm/°C]: growth per sensor error through a steady-state H fit (sensors -> H -> field).

    ``prior_rel``: a prior of that relative 1σ on every H (MAP fit with sensor noise ``noise_c`` [°C]);
    None: plain least squares.
    """
    qf = float(bearing_heat_w(speed_rpm, 0.0, spec.bearings.front))
    qr = float(bearing_heat_w(speed_rpm, 0.0, spec.bearings.rear))
    jac = steady_jacobian_h(fe, H_TABLE4, ambient_c=AMBIENT_C, q_front_w=qf, q_rear_w=qr)
    if prior_rel is None:
        return sensor_sensitivity(gm.operators, reconstruction_h_fit(fe, jac))
    prior = np.diag((prior_rel * np.asarray(H_TABLE4)) ** 2)
    return sensor_sensitivity(gm.operators, reconstruction_h_fit(fe, jac, noise_c=noise_c, prior_cov_h=prior))


REGION_CHARS = {
    "shaft_rear_journal": "s",
    "shaft_body": "s",
    "shaft_nose": "s",
    "pulley": "p",
    "rear_end_cap": "c",
    "front_end_cap": "c",
    "housing": "H",
    "rear_bearing": "R",
    "front_bearing_a": "F",
    "front_bearing_b": "F",
    "spacer": "x",
}


def section_sketch(spec: SpindleSpec, *, dz_m: float = 0.006, dr_m: float = 0.005) -> str:
    """Text figure of the (r, z) half-section with the mechanical boundary conditions and outputs.

    One character per dz x dr cell (region at the cell centre, ``REGION_CHARS``, else '#'); '~' marks the
    floating surface, 'v' the mounting face, '*' the outputs, '=' the axis (u_r = 0).
    """
    mech = spec.mechanics
    z_max, r_max = max(g.z1_m for g in spec.regions), max(g.r1_m for g in spec.regions)
    nz, nr = round(z_max / dz_m), round(r_max / dr_m)
    grid = [[" "] * nz for _ in range(nr)]
    for i in range(nr):
        for j in range(nz):
            r, z = (i + 0.5) * dr_m, (j + 0.5) * dz_m
            hit = next((g for g in spec.regions if g.contains(r, z, tol=0.0)), None)
            grid[i][j] = " " if hit is None else REGION_CHARS.get(hit.name, "#")
    top = [" "] * nz
    if mech is not None:
        for fl in mech.floating:
            g = next(x for x in spec.regions if x.name == fl.region)
            outer = fl.surface == "outer"
            row = min(int((g.r1_m if outer else g.r0_m) / dr_m) - int(outer), nr - 1)
            for j in range(int(g.z0_m / dz_m), int(np.ceil(g.z1_m / dz_m))):
                grid[row][j] = "~"
        for seg in mech.mount.segments:
            j = min(int(seg.z0_m / dz_m), nz - 1)
            top[j] = "v"
        for out in mech.outputs:
            i, j = (max(0, int(np.ceil(x / d - 1e-9)) - 1) for x, d in ((out.r_m, dr_m), (out.z_m, dz_m)))
            grid[min(i, nr - 1)][min(j, nz - 1)] = "*"
    lines = ["       " + "".join(top)]
    lines += [f"{(i + 1) * dr_m * 1e3:5.0f} |" + "".join(grid[i]) for i in reversed(range(nr))]
    lines.append("    0 =" + "=" * nz + " axis")
    ticks = [" "] * (nz + 4)
    for z_mm in range(0, int(z_max * 1e3) + 1, 100):
        label = str(z_mm)
        j = int(z_mm * 1e-3 / dz_m)
        ticks[j : j + len(label)] = list(label)
    lines.append("  z mm " + "".join(ticks).rstrip())
    return "\n".join(lines)


SECTIONS = ("mesh", "one_d", "variants", "eval", "sensitivity", "sketch")


def main(argv: Sequence[str] | None = None) -> None:
    """Print the studies (markdown-ish tables or one JSON object)."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.005, 0.004, 0.003, 0.0025, 0.002, 0.0015])
    ap.add_argument("--ref", type=float, default=0.001)
    ap.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS), help="sections to run")
    args = ap.parse_args(argv)
    spec = load_spindle()
    fe = build_fe_model(spec)
    gm = build_growth_model(spec, fe)
    studies: dict[str, Any] = {
        "mesh": lambda: [asdict(r) for r in mesh_study(spec, sizes_m=args.sizes, reference_m=args.ref)],
        "one_d": lambda: one_d_table(spec, fe, gm, realistic_fields(spec, fe)),
        "variants": lambda: variant_table(fe),
        "eval": lambda: eval_cost_us(gm),
        "sensitivity": lambda: {
            label: dict(zip(gm.names, sensitivity_table(spec, fe, gm, prior_rel=p).tolist(), strict=True))
            for label, p in (("least_squares", None), ("prior_30pct", 0.3))
        },
        "sketch": lambda: section_sketch(spec),
    }
    out = {name: studies[name]() for name in SECTIONS if name in args.only}
    if args.json:
        print(json.dumps(out, indent=1))
        return
    for section, rows in out.items():
        print(f"## {section}")
        if isinstance(rows, str):
            print(rows)
            continue
        for row in rows if isinstance(rows, list) else [rows]:
            print(row)


if __name__ == "__main__":
    main()
