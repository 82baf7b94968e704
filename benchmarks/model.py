"""``python -m benchmarks model``: speed and accuracy of the full FE model and of the reduced model, in one
run.

Figures (one 60-min window = 360 steps of 10 s, the service's default mesh unless told otherwise):

- ``full_forward_ms``: one full-FE θ-method window (factorisation + 360 solves, sensors only), median of runs;
  the full FE and the reduced model are timed in turns (one FE window, then the ROM calls, ``--runs`` times),
  so that a change of the machine's load between the two moves both sides of each ratio;
- ``full_vs_reference_max_err_c``: the default mesh against a much finer mesh at the 32 sensors, on the
  paper's two H sets and one random H, with a heat step and an ambient drift inside the window;
- ``rom_forward_ms`` (one candidate) and ``rom_batched_ms_per_candidate`` (population of 28), medians;
- ``rom_max_err_c``: reduced vs full FE at the sensors over ``--check`` random H in the box (two random input
  histories each: uniform start and non-uniform start), not used in training;
- ``rom_vs_converged_max_err_c``: the reduced model *as served* (its own time integration, ``rom_substeps``;
  0 = exact over each held step) vs the full FE converged in time (Richardson extrapolation of backward Euler
  at Δt/20 and Δt/40; ``converged_reference_time_err_c`` bounds the reference's own error) over
  ``--converged-check`` random H, 10-min windows (the model error budget of issue 15: target ≤ 0.02 °C);
- ``rom_build_s`` (fresh build into a temporary cache), ``rom_load_s`` (loading that cache file);
- ``speedup_rom_vs_full``: the median over the turns of full_forward_ms / rom_batched_ms_per_candidate (each
  turn's own pair; ``speedup_rom_single_vs_full`` likewise for one candidate; ``timing_turns`` lists each
  turn's times);
- ``growth_build_s``, ``growth_eval_us``, ``growth_eval_reduced_us``: the thermal-growth operators
  (docs/design/growth.md): build time, and one evaluation of all outputs from a field / from a reduced state.

Progress goes to stderr; ``--json`` prints one JSON object, otherwise a table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from benchmarks.targets import Target, format_verdicts, verdicts

if TYPE_CHECKING:
    from model.fem import FEModel
    from model.geometry import SpindleSpec
    from model.inputs import InputSeries
    from model.rom import ReducedModel

TARGETS = (  # docs/design/rom.md, "Target check"
    Target("full_vs_reference_max_err_c", "<=", 0.02, unit="°C"),
    Target("rom_max_err_c", "<=", 0.05, unit="°C"),
    # issue 15's model error budget (docs/design/rom.md)
    Target("rom_vs_converged_max_err_c", "<=", 0.02, unit="°C"),
    Target("speedup_rom_vs_full", ">=", 500.0, unit="x"),
    Target("rom_build_s", "<=", 60.0, unit="s"),
    Target("rom_load_s", "<=", 1.0, unit="s"),
)

CONVERGED_STEPS = 60  # 10-min windows: every jump's first steps, at an affordable cost for 2 × 60 substeps
CONVERGED_SUBSTEPS = 20  # reference: Richardson of backward Euler at 0.5 s and 0.25 s (model.rom_check)
PAPER_H = (
    (88.21, 46.32, 68.49, 46.72, 52.13, 70.23, 16.54),  # Table 4, 3000 rpm
    (79.75, 46.25, 61.89, 45.31, 46.20, 68.23, 11.12),  # Table 10, 4000 rpm
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks model``."""
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--runs",
        type=int,
        default=5,
        help="timing turns (full FE, then the reduced model; medians), default 5",
    )
    parser.add_argument("--check", type=int, default=100, help="random H for rom_max_err_c (>= 100 advised)")
    parser.add_argument(
        "--rank", type=int, default=None, help="reduced-model rank (default: model.rom default)"
    )
    parser.add_argument("--mesh-size-m", type=float, default=None, help="FE mesh size [m] (default: spec's)")
    parser.add_argument(
        "--reference-mesh-size-m",
        type=float,
        default=None,
        help="reference mesh size [m] (default: 0.4 x mesh)",
    )
    parser.add_argument("--seed", type=int, default=12345, help="seed of the random check cases")
    parser.add_argument(
        "--converged-check",
        type=int,
        default=20,
        help="random H for rom_vs_converged_max_err_c (served ROM vs a time-converged full FE), default 20",
    )


def _median_ms(fn: Callable[[], Any], runs: int) -> float:
    times = []
    for _ in range(max(1, runs)):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return 1e3 * statistics.median(times)


def _window(n_steps: int = 360) -> InputSeries:
    """A 60-min window: front/rear heat step after 20 min, ambient drifting by 1 °C."""
    from model.inputs import InputSeries

    k = np.arange(n_steps)
    return InputSeries(
        10.0,
        21.8 + k / n_steps,
        np.where(k < 120, 80.0, 200.0),
        np.where(k < 120, 40.0, 110.0),
    )


def _progress(text: str) -> None:
    print(f"[bench model {time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)


def _full_figures(fe: FEModel, spec: SpindleSpec, args: argparse.Namespace) -> dict[str, Any]:
    from model.fem import build_fe_model, simulate_sensors

    inputs = _window()
    ref_size = args.reference_mesh_size_m or 0.4 * fe.mesh_size_m
    _progress(f"reference mesh {ref_size:.5f} m")
    ref = build_fe_model(spec, mesh_size_m=ref_size)
    rng = np.random.default_rng(args.seed)
    lo, hi = spec.h_box
    hs = [np.asarray(x) for x in PAPER_H] + [lo * (hi / lo) ** rng.random(7)]
    errs = []
    for i, hh in enumerate(hs):
        coarse, _ = simulate_sensors(fe, hh, inputs, 21.8)
        fine, _ = simulate_sensors(ref, hh, inputs, 21.8)
        errs.append(float(np.max(np.abs(coarse - fine))))
        _progress(f"reference case {i + 1}/{len(hs)}: {errs[-1]:.4f} °C")
    return {
        "reference_nodes": int(ref.n_nodes),
        "reference_mesh_size_m": ref_size,
        "full_vs_reference_max_err_c": max(errs),
    }


def _speed_figures(fe: FEModel, rom: ReducedModel, args: argparse.Namespace) -> dict[str, Any]:
    """Full FE (one window) and reduced model (one candidate; a population of 28) timed in turns, ``--runs``
    turns: medians of the times [ms] and of the per-turn ratios (the speed-ups)."""
    from model.fem import simulate_sensors

    inputs = _window()
    h = np.asarray(PAPER_H[0])
    rng = np.random.default_rng(args.seed)
    lo, hi = rom.h_box
    pop = lo * (hi / lo) ** rng.random((28, 7))
    simulate_sensors(fe, h, inputs, 21.8)  # warm-up, untimed: first-call costs on both sides
    rom.simulate_sensors(pop, inputs, 21.8)
    full, one, batch = [], [], []
    for _ in range(max(1, args.runs)):
        full.append(_median_ms(lambda: simulate_sensors(fe, h, inputs, 21.8), 1))
        one.append(_median_ms(lambda: rom.simulate_sensors(pop[:1], inputs, 21.8), 10))
        batch.append(_median_ms(lambda: rom.simulate_sensors(pop, inputs, 21.8), 4) / 28)
    return {
        "full_forward_ms": statistics.median(full),
        "rom_forward_ms": statistics.median(one),
        "rom_batched_ms_per_candidate": statistics.median(batch),
        "speedup_rom_vs_full": statistics.median(f / b for f, b in zip(full, batch, strict=True)),
        "speedup_rom_single_vs_full": statistics.median(f / o for f, o in zip(full, one, strict=True)),
        "timing_turns": {"full_ms": full, "rom_ms_per_candidate": batch, "rom_single_ms": one},
    }


def _rom_figures(
    fe: FEModel, spec: SpindleSpec, args: argparse.Namespace
) -> tuple[dict[str, Any], ReducedModel]:
    from model import rom_check
    from model.rom import load_or_build_rom

    opts: dict[str, Any] = {} if args.rank is None else {"rank": args.rank}
    with tempfile.TemporaryDirectory(prefix="chtc-bench-rom-") as tmp:
        _progress("building the reduced model (fresh cache)")
        started = time.perf_counter()
        built = load_or_build_rom(fe, spec, Path(tmp), progress=_progress, **opts)
        build_s = time.perf_counter() - started
        started = time.perf_counter()
        rom = load_or_build_rom(fe, spec, Path(tmp), **opts)
        load_s = time.perf_counter() - started
    if not rom.from_cache:
        raise RuntimeError("reduced model was not reloaded from its cache file")
    _progress(f"checking the reduced model on {args.check} random H (2 histories each)")
    report = rom_check.error_report(
        replace(rom, substeps=1),  # projection error: the ROM and the full FE take the same θ-steps
        fe,
        theta=rom.theta,
        box=rom.h_box,
        n_cases=args.check,
        seed=args.seed,
        q_max_w=tuple(built.error_report.get("q_max_w", (300.0, 150.0))),
        progress=_progress,
    )
    _progress(f"checking the served reduced model against a converged full FE on {args.converged_check} H")
    conv = rom_check.error_report(
        rom,
        fe,
        theta=rom.theta,
        box=rom.h_box,
        n_cases=args.converged_check,
        seed=args.seed + 1,
        q_max_w=tuple(built.error_report.get("q_max_w", (300.0, 150.0))),
        n_steps=CONVERGED_STEPS,
        ref_substeps=CONVERGED_SUBSTEPS,
        progress=_progress,
    )
    figures = {
        "rom_size": rom.rank,
        "rom_substeps": rom.substeps,
        "rom_vs_converged_max_err_c": conv["max_err_c"],
        "rom_vs_converged_p95_err_c": conv["p95_err_c"],
        "converged_reference_time_err_c": conv["ref_time_err_c"],
        "converged_check_h": conv["n_cases"],
        "rom_max_err_c": report["max_err_c"],
        "rom_mean_err_c": report["mean_err_c"],
        "rom_p95_err_c": report["p95_err_c"],
        "rom_max_err_uniform_start_c": report["max_err_uniform_start_c"],
        "rom_max_err_field_start_c": report["max_err_field_start_c"],
        "rom_check_h": report["n_cases"],
        "rom_check_histories": report["n_histories"],
        "rom_build_reported_err_c": built.error_report["max_err_c"],
        "rom_build_s": build_s,
        "rom_load_s": load_s,
    }
    return figures, rom


def _growth_figures(fe: FEModel, spec: SpindleSpec) -> dict[str, Any]:
    """Thermal growth (docs/design/growth.md): operator build time [s] and one evaluation [µs], nodal and
    reduced."""
    from benchmarks.studies.growth_check import eval_cost_us
    from model.thermoelastic import build_growth_model

    started = time.perf_counter()
    gm = build_growth_model(spec, fe)
    build_s = time.perf_counter() - started
    cost = eval_cost_us(gm)
    return {
        "growth_build_s": build_s,
        "growth_eval_us": cost["nodal_us"],
        "growth_eval_reduced_us": cost["reduced_us"],
        "growth_outputs": list(gm.names),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """All figures as one dict (times in ms or s, errors in °C)."""
    from model.fem import build_fe_model
    from model.geometry import load_spindle

    spec = load_spindle()
    fe = build_fe_model(spec, mesh_size_m=args.mesh_size_m)
    _progress(f"FE model: {fe.n_nodes} nodes")
    out: dict[str, Any] = {"mesh_nodes": int(fe.n_nodes), "mesh_size_m": fe.mesh_size_m, "window_steps": 360}
    out["window_dt_s"] = 10.0
    out.update(_full_figures(fe, spec, args))
    rom_figures, rom = _rom_figures(fe, spec, args)
    out.update(rom_figures)
    _progress(f"timing the full FE and the reduced model in turns ({args.runs} turns)")
    out["load_avg_1m_start"] = os.getloadavg()[0]
    out.update(_speed_figures(fe, rom, args))
    out.update(_growth_figures(fe, spec))
    out["runs"] = args.runs
    out["load_avg_1m"] = os.getloadavg()[0]  # other work on the machine inflates every timing
    out["timestamp_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    out["targets"] = verdicts(TARGETS, out)
    return out


def format_table(res: dict[str, Any]) -> str:
    """A readable table of the figures."""
    rows = [
        ("FE mesh", f"{res['mesh_nodes']} nodes ({res['mesh_size_m'] * 1e3:.2f} mm)"),
        ("full FE, one 60-min window", f"{res['full_forward_ms']:.1f} ms"),
        ("reference mesh", f"{res['reference_nodes']} nodes ({res['reference_mesh_size_m'] * 1e3:.2f} mm)"),
        ("full FE vs reference (sensors)", f"{res['full_vs_reference_max_err_c']:.4f} °C max"),
        ("reduced model rank", f"{res['rom_size']}"),
        ("ROM, one candidate", f"{res['rom_forward_ms']:.3f} ms"),
        ("ROM, population of 28", f"{res['rom_batched_ms_per_candidate']:.3f} ms per candidate"),
        (
            f"ROM projection vs full FE ({res['rom_check_h']} H)",
            f"{res['rom_max_err_c']:.4f} °C max, {res['rom_p95_err_c']:.4f} p95, "
            f"{res['rom_mean_err_c']:.4f} mean",
        ),
        (
            f"served ROM vs converged FE ({res['converged_check_h']} H)",
            f"{res['rom_vs_converged_max_err_c']:.4f} °C max, {res['rom_vs_converged_p95_err_c']:.4f} p95 "
            f"(reference's own time error ≤ {res['converged_reference_time_err_c']:.4f} °C)",
        ),
        ("ROM build / load", f"{res['rom_build_s']:.1f} s / {res['rom_load_s'] * 1e3:.0f} ms"),
        ("speed-up ROM (batched) vs full", f"{res['speedup_rom_vs_full']:.0f}x"),
        ("speed-up ROM (single) vs full", f"{res['speedup_rom_single_vs_full']:.0f}x"),
        (
            "growth: build / one evaluation",
            f"{res['growth_build_s']:.2f} s / {res['growth_eval_us']:.1f} µs nodal, "
            f"{res['growth_eval_reduced_us']:.2f} µs reduced",
        ),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [
        f"python -m benchmarks model ({res['timestamp_utc']}, medians of {res['runs']} timing turns, "
        f"load average {res['load_avg_1m_start']:.1f} at the timing, {res['load_avg_1m']:.1f} at the end)"
    ]
    lines += [f"  {k.ljust(width)}  {v}" for k, v in rows]
    lines.append(format_verdicts(res["targets"]))
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Run ``python -m benchmarks model``."""
    res = run(args)
    print(json.dumps(res, indent=2) if args.json else format_table(res), flush=True)
    return 0
