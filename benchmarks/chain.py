"""``python -m benchmarks chain``: accuracy of the *running service's* answers over a chain of operating
conditions.

``python -m benchmarks identify`` fits one window that starts from the plant's true (uniform) initial field.
The service cannot do that after the first condition: each window starts from its live state, which was
advanced with earlier, imperfect H (``service.estimate.live``). This bench measures what that costs.

Data are SYNTHETIC: per seed the virtual plant (finer mesh, its own truth ``model.plant.h_true``, σ = 0.15 °C)
runs the end-to-end test's profile (5 min idle, then 3000 → 4000 → 5000 rpm, 45 min each, from a cold
spindle), and the samples go through the service's own core offline (``service.core.offline.run_offline``:
detector, scheduler, live state, windows, identification; deterministic). For the last identification of
each condition (the 40-min window) it reports, per H, the median and maximum relative error against the truth
over the seeds, the median relative 95 % half-width of the CI as served (with the carried start-field error
unless ``experimental.carry_start_error`` is false), the fraction of seeds whose CI covers the truth, and
the fraction whose CIs cover all seven H at once.

``--mode per_condition|speed_map|combined`` and ``--set KEY=VALUE`` choose the identification mode and
settings (``benchmarks.identmode``; default: the settings' ``identification.mode``), reported as
``mode``. In speed-map mode the last identification of a condition is the last map fit launched at it (its
window: the rolling ``map_window_min``, up to 60 min, across the earlier conditions), served at the
condition; in combined mode the condition's own per-condition one (``identmode.served_in_order``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import numpy as np

from benchmarks import identmode
from benchmarks.targets import Target, format_verdicts, progress_to_stderr, report, verdicts
from service.contracts.mode import IdentificationMode

if TYPE_CHECKING:
    from drivers.ringbuffer import Sample
    from service.contracts.snapshots import IdentificationRecord

TARGETS_NOTE = "mean over H1-H7, every condition; the nominal 95 % range python -m benchmarks identify uses"
TARGETS = (Target("ci_coverage_mean_worst", "in", (0.85, 1.0), note=TARGETS_NOTE),)
PROFILE = (
    (300.0, 0.0, 0.0, 23.2),  # idle and cold: the service is up before the spindle runs
    (2700.0, 3000.0, 5.0, 23.2),
    (2700.0, 4000.0, 6.0, 21.8),
    (2700.0, 5000.0, 8.0, 22.0),
)
T0 = datetime(2026, 1, 5, 8, 0, 0, tzinfo=UTC).timestamp()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks chain``."""
    parser.add_argument("--seeds", type=int, default=8, help="virtual-plant noise seeds (default 8)")
    identmode.add_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def plant_samples(seed: int) -> list[Sample]:
    """The profile's plant run as acquisition samples every 10 s."""
    from model.geometry import load_spindle
    from model.plant import Segment, VirtualPlant
    from simulator.plantsamples import samples_from_plant

    run = VirtualPlant(load_spindle(), seed=seed).run([Segment(*s) for s in PROFILE], dt_s=10.0)
    return samples_from_plant(run, t0_s=T0)


def last_per_condition(records: list[IdentificationRecord]) -> dict[float, IdentificationRecord]:
    """The last successful identification served at each condition (``identmode.served_in_order``: in combined
    mode the per-condition one), keyed by its speed (rounded to 100 rpm)."""
    out: dict[float, IdentificationRecord] = {}
    for rec in identmode.served_in_order(records):  # oldest first
        out[round(rec.condition.speed_rpm, -2)] = rec
    return out


def summarise(errors: np.ndarray, half_widths: np.ndarray, covered: np.ndarray) -> dict[str, Any]:
    """Per-H figures over seeds, the fraction of seeds whose CIs cover all / all but one H, and each seed's
    median |error| over the seven H (its median and maximum over seeds: what one run's answer is judged by);
    inputs (seeds, 7)."""
    misses = np.sum(~np.asarray(covered, dtype=bool), axis=1)
    per_seed = np.median(np.abs(errors), axis=1)
    return {
        "h_err_pct_median": np.round(100 * np.median(np.abs(errors), axis=0), 1).tolist(),
        "h_err_pct_max": np.round(100 * np.max(np.abs(errors), axis=0), 1).tolist(),
        "ci_half_width_pct_median": np.round(100 * np.median(half_widths, axis=0), 1).tolist(),
        "ci_coverage": np.round(np.mean(covered, axis=0), 2).tolist(),
        "ci_covers_all": round(float(np.mean(misses == 0)), 2),
        "ci_covers_all_but_one": round(float(np.mean(misses <= 1)), 2),
        "seed_median_err_pct_median": round(100 * float(np.median(per_seed)), 1),
        "seed_median_err_pct_max": round(100 * float(np.max(per_seed)), 1),
    }


def run(
    seeds: int,
    *,
    ident_mode: str | None = None,
    overrides: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """``ident_mode`` None: the settings' ``identification.mode``; ``overrides``: ``--set`` settings."""
    from model.plant import h_true
    from service.core.offline import run_offline
    from service.host.runtime import core_config
    from service.modelload import ModelRef, load_model

    settings = identmode.bench_settings(ident_mode, overrides)
    ident = settings.identification
    model = load_model(ModelRef.from_settings(settings))
    rows: dict[float, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    started = time.perf_counter()
    for seed in range(seeds):
        result = run_offline(plant_samples(seed), model=model, config=core_config(settings))
        for speed, rec in last_per_condition(result.records).items():
            truth = h_true(rec.condition.speed_rpm, rec.condition.ambient_c)
            h, lo, hi = (np.asarray(a, dtype=float) for a in (rec.h, rec.ci95_lo, rec.ci95_hi))
            rows.setdefault(speed, []).append(
                ((h - truth) / truth, (hi - lo) / 2 / h, (lo <= truth) & (truth <= hi))
            )
        if progress is not None:
            progress(f"seed {seed + 1}/{seeds} done ({time.perf_counter() - started:.0f} s)")
    conditions = []
    for _, speed, torque, ambient in PROFILE:
        items = rows.get(speed, [])
        if not items:
            continue
        err, half, cov = (np.array([it[i] for it in items]) for i in range(3))
        conditions.append(
            {"speed_rpm": speed, "torque_nm": torque, "ambient_c": ambient, "seeds": len(items)}
            | summarise(err, half, cov)
        )
    worst = min((float(np.mean(c["ci_coverage"])) for c in conditions), default=None)
    return {
        "synthetic": True,
        "mode": settings.identification.mode,
        "settings": overrides or {},
        "window_min": (
            ident.map_window_min if settings.identification.mode is IdentificationMode.SPEED_MAP else 40
        ),
        "conditions": conditions,
        "targets": verdicts(TARGETS, {"ci_coverage_mean_worst": worst}),
        "wall_s": round(time.perf_counter() - started, 1),
    }


def _print_table(out: dict[str, Any]) -> None:
    print(
        f"last identification per condition (window up to {out['window_min']:g} min), mode {out['mode']}, "
        f"chained through the service core; synthetic data; wall {out['wall_s']} s"
    )
    head = "".join(f"{'H' + str(i + 1):>8}" for i in range(7))
    for c in out["conditions"]:
        print(f"\n{c['speed_rpm']:.0f} rpm, {c['torque_nm']} N·m, {c['ambient_c']} °C ({c['seeds']} seeds)")
        print(f"{'':28}{head}")
        for key, label in (
            ("h_err_pct_median", "median |error| %"),
            ("h_err_pct_max", "max |error| %"),
            ("ci_half_width_pct_median", "median CI half-width %"),
            ("ci_coverage", "95 % CI coverage"),
        ):
            print(
                f"{label:28}" + "".join(f"{v:8.2f}" if key == "ci_coverage" else f"{v:8.1f}" for v in c[key])
            )
        print(
            f"seeds whose CIs cover all {len(c['ci_coverage'])} H: {c['ci_covers_all']:.2f}, "
            f"all but one: {c['ci_covers_all_but_one']:.2f}; a seed's median |error| over the H: "
            f"median {c['seed_median_err_pct_median']:.1f} %, max {c['seed_median_err_pct_max']:.1f} %"
        )
    print(format_verdicts(out["targets"]))


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        print("error: --seeds must be >= 1", file=sys.stderr)
        return 2
    try:
        overrides = identmode.parse_sets(args.set)
        out = run(args.seeds, ident_mode=args.ident_mode, overrides=overrides, progress=progress_to_stderr)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return report(out, as_json=args.json, table=_print_table)
