"""Mesh study of the FE model: nodes, forward time and sensor error against a much finer reference.

``mesh_study`` is pure (returns rows); ``python -m benchmarks.studies.fe_check`` prints them (``--json`` for
JSON). The scenario is a 60-min run (360 steps of 10 s) from a uniform field at the paper's Table 4 H.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from model.fem import build_fe_model, simulate_sensors
from model.geometry import SpindleSpec, load_spindle
from model.inputs import inputs_from_operation

H_TABLE4 = (88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54)


@dataclass(frozen=True)
class StudyRow:
    """One mesh: size [m], nodes, median forward time [s], max/RMS sensor error vs the reference [degC]."""

    mesh_size_m: float
    n_nodes: int
    forward_s: float
    max_err_c: float
    rms_err_c: float
    max_rise_c: float


def _run(
    spec: SpindleSpec, size: float, *, speed_rpm: float, torque_nm: float, repeats: int
) -> tuple[int, float, NDArray[np.float64]]:
    fe = build_fe_model(spec, mesh_size_m=size)
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=np.full(360, speed_rpm), torque_nm=torque_nm, ambient_c=23.2
    )
    times, sens = [], np.zeros(0)
    for _ in range(repeats):
        t = time.perf_counter()
        sens, _ = simulate_sensors(fe, np.array(H_TABLE4), inputs, 23.2)
        times.append(time.perf_counter() - t)
    return fe.n_nodes, float(np.median(times)), sens


def mesh_study(
    spec: SpindleSpec,
    sizes_m: Sequence[float],
    *,
    ref_size_m: float = 0.00075,
    speed_rpm: float = 5000.0,
    torque_nm: float = 10.0,
    repeats: int = 3,
) -> list[StudyRow]:
    """Compare meshes of ``sizes_m`` [m] with a reference mesh of ``ref_size_m`` [m] at the sensors."""
    _, _, ref = _run(spec, ref_size_m, speed_rpm=speed_rpm, torque_nm=torque_nm, repeats=1)
    rows = []
    for size in sizes_m:
        n, t, sens = _run(spec, size, speed_rpm=speed_rpm, torque_nm=torque_nm, repeats=repeats)
        err = sens - ref
        rows.append(
            StudyRow(
                size, n, t, float(np.abs(err).max()), float(np.sqrt(np.mean(err**2))), float(np.ptp(ref))
            )
        )
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """Command line:
    ``python -m benchmarks.studies.fe_check [--sizes ...] [--ref M] [--speed RPM] [--json]``."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.004, 0.003, 0.0025, 0.002])
    ap.add_argument("--ref", type=float, default=0.00075, help="reference mesh size [m]")
    ap.add_argument("--speed", type=float, default=5000.0, help="speed [rpm]")
    ap.add_argument("--torque", type=float, default=10.0, help="torque [N m]")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = mesh_study(
        load_spindle(),
        args.sizes,
        ref_size_m=args.ref,
        speed_rpm=args.speed,
        torque_nm=args.torque,
        repeats=args.repeats,
    )
    if args.json:
        print(json.dumps([asdict(r) for r in rows], indent=2))
        return 0
    print(f"reference mesh {args.ref * 1e3:.2f} mm; {args.speed:.0f} rpm, {args.torque:.1f} N m, 360 x 10 s")
    print(f"{'size mm':>8} {'nodes':>7} {'forward ms':>11} {'max err degC':>13} {'rms err degC':>13}")
    for r in rows:
        print(
            f"{r.mesh_size_m * 1e3:8.2f} {r.n_nodes:7d} {r.forward_s * 1e3:11.1f} {r.max_err_c:13.4f}"
            f" {r.rms_err_c:13.4f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
