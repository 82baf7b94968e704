"""``python -m benchmarks duty``: the served H over a machining duty cycle (issue 17), against the plant's
truth.

Data are SYNTHETIC: per seed a duty cycle (``simulator.duty``: 5 min idle, then the speed changes every
1–6 min among 0, 500, …, 7000 rpm, torque 3–15 N·m, ambient drifting ±1 °C; 4 h by default) runs on the
virtual plant (finer mesh, its own truth ``model.plant.h_true``, σ = 0.15 °C, default settings). The samples
go through the running service's own shell and core (``SoftSensorService`` with the identification run inline,
as offline), in the settings' ``identification.mode`` (``combined`` by default: a held condition's own
per-condition H once it has one, the speed map's elsewhere), or ``--mode speed_map`` or ``per_condition``
(the paper's protocol).
Every minute the bench reads ``/chtc`` (``SoftSensorService.chtc()``) and compares each served H with the
plant's ``h_true`` at the plant's condition at that minute (speed and ambient).

Printed, over the seeds (minutes after the first ``--warmup-min``, 30): the fraction of minutes with a fresh
H (status ``fresh``), the longest gap without one (min), per H the median |error| of the fresh H, the coverage
of their 95 % CI, the fraction of them flagged identified (CI narrower than ``ci_rel_threshold``), and the
identification wall time (median, max) with the model runs: of the map fits where there is a map, else of
the per-condition identifications. In combined mode also the per-condition identifications per seed, their
wall time and the fraction of the fresh minutes they served.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from benchmarks import identmode
from benchmarks.targets import progress_to_stderr, report
from service.contracts.mode import IdentificationMode
from service.contracts.verdict import ChtcStatus

T0 = datetime(2026, 3, 2, 6, 0, 0, tzinfo=UTC).timestamp()
DT_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks duty``."""
    parser.add_argument("--seeds", type=int, default=3, help="duty cycles (seeds), default 3")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (split a long run), default 0")
    parser.add_argument("--hours", type=float, default=4.0, help="duty cycle length incl. 5 min idle (4 h)")
    parser.add_argument("--warmup-min", type=float, default=30.0, help="minutes not counted (30)")
    identmode.add_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")


@dataclass(kw_only=True)
class SeedResult:
    """One seed's per-minute comparison (minutes after the warm-up)."""

    fresh: list[bool] = field(default_factory=list)
    err: list[np.ndarray] = field(default_factory=list)  # (7,) relative error of fresh H
    covered: list[np.ndarray] = field(default_factory=list)  # (7,) bool
    identified: list[np.ndarray] = field(default_factory=list)  # (7,) bool
    wall_s: list[float] = field(default_factory=list)  # map fits (per-condition ones without a map)
    nfev: list[int] = field(default_factory=list)
    fits: int = 0
    held_wall_s: list[float] = field(default_factory=list)  # combined mode: the per-condition ones
    held_served: list[bool] = field(default_factory=list)  # per fresh minute: a per-condition one served
    not_fresh: dict[str, int] = field(default_factory=dict)  # minutes by reason code


def longest_gap(fresh: list[bool]) -> int:
    """Longest run of minutes without a fresh H."""
    longest = run = 0
    for f in fresh:
        run = 0 if f else run + 1
        longest = max(longest, run)
    return longest


def run_seed(model: Any, settings: Any, seed: int, *, hours: float, warmup_min: float) -> SeedResult:
    """One duty cycle through the service (module docstring)."""
    from model.geometry import load_spindle
    from model.plant import VirtualPlant, h_true
    from service.core.jobbook import MAP_METHOD
    from service.core.machine import ServiceCore
    from service.host.runtime import core_config
    from service.identify.worker import run_job
    from service.shell.service import SoftSensorService
    from simulator.duty import condition_at, duty_profile
    from simulator.plantsamples import samples_from_plant
    from simulator.served import ManualClock

    profile = duty_profile(seed, duration_s=3600.0 * hours)
    run = VirtualPlant(load_spindle(), seed=seed).run(profile, dt_s=DT_S)
    samples = samples_from_plant(run, t0_s=T0)
    core = ServiceCore(core_config(settings), model=model, history_capacity=100_000)
    clock = ManualClock(samples[0].t)
    svc = SoftSensorService(
        core, worker=None, clock=clock, on_event=lambda _m: None, run_job=lambda req: run_job(model, req)
    )
    out = SeedResult()
    per_min = round(60.0 / DT_S)
    for k, sample in enumerate(samples):
        clock.at_least(sample.t)
        svc.on_sample(sample)
        t_plant = float(run.times_s[k])
        if k % per_min or t_plant < 60.0 * warmup_min:
            continue
        seg = condition_at(profile, t_plant)
        truth = np.asarray(h_true(seg.speed_rpm, seg.ambient_c), dtype=float)
        snap = svc.chtc()
        fresh = snap is not None and snap.status is ChtcStatus.FRESH
        out.fresh.append(fresh)
        if not fresh:
            code = "none" if snap is None else (snap.verdict.reason or snap.status).value
            out.not_fresh[code] = out.not_fresh.get(code, 0) + 1
        if snap is not None and fresh:
            h, lo, hi = (np.asarray(a, dtype=float) for a in (snap.h, snap.ci95_lo, snap.ci95_hi))
            out.err.append(h / truth - 1.0)
            out.covered.append((lo <= truth) & (truth <= hi))
            out.identified.append(np.asarray(snap.identified, dtype=bool))
            out.held_served.append(snap.record.method != MAP_METHOD)
    combined = svc.identification_mode() is IdentificationMode.COMBINED
    for rec in svc.view.records:
        if rec.outcome != "ok":
            continue
        if combined and rec.method != MAP_METHOD:
            out.held_wall_s.append(float(rec.wall_s))
            continue
        out.fits += 1
        out.wall_s.append(float(rec.wall_s))
        out.nfev.append(int(rec.nfev))
    return out


def summarise(results: list[SeedResult]) -> dict[str, Any]:
    fresh = [f for r in results for f in r.fresh]
    err = np.array([e for r in results for e in r.err]).reshape(-1, 7)
    cov = np.array([c for r in results for c in r.covered]).reshape(-1, 7)
    ident = np.array([i for r in results for i in r.identified]).reshape(-1, 7)
    wall = [w for r in results for w in r.wall_s]
    held = [w for r in results for w in r.held_wall_s]
    served = [s for r in results for s in r.held_served]
    nfev = [n for r in results for n in r.nfev]

    def per_h(a: np.ndarray, f: Any, nd: int) -> list[float | None]:
        return [None if a.shape[0] == 0 else round(float(f(a[:, i])), nd) for i in range(7)]

    return {
        "fresh_fraction": round(float(np.mean(fresh)), 3) if fresh else 0.0,
        "fresh_fraction_min_seed": round(min(float(np.mean(r.fresh)) for r in results if r.fresh), 3)
        if any(r.fresh for r in results)
        else 0.0,
        "longest_gap_min": max(longest_gap(r.fresh) for r in results),
        "coverage": per_h(cov, np.mean, 3),
        "h_err_pct_median": per_h(100 * np.abs(err), np.median, 1),
        "h_err_pct_p90": per_h(100 * np.abs(err), lambda x: np.percentile(x, 90), 1),
        "identified_fraction": per_h(ident, np.mean, 3),
        "identify_wall_s_median": round(float(np.median(wall)), 3) if wall else None,
        "identify_wall_s_max": round(float(np.max(wall)), 3) if wall else None,
        "identify_wall_s_p90": round(float(np.percentile(wall, 90)), 3) if wall else None,
        "model_runs_median": float(np.median(nfev)) if nfev else None,
        "model_runs_max": int(np.max(nfev)) if nfev else None,
        "fits_per_seed": round(float(np.mean([r.fits for r in results])), 1),
        "fresh_minutes": int(err.shape[0]),
        "per_condition_fits_per_seed": round(float(np.mean([len(r.held_wall_s) for r in results])), 1),
        "per_condition_wall_s_median": round(float(np.median(held)), 3) if held else None,
        "per_condition_wall_s_max": round(float(np.max(held)), 3) if held else None,
        "per_condition_served_fraction": round(float(np.mean(served)), 3) if served else 0.0,
        "not_fresh_minutes": _sum_counts([r.not_fresh for r in results]),
    }


def _sum_counts(counts: list[dict[str, int]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for c in counts:
        for k, v in c.items():
            out[k] = out.get(k, 0) + v
    return dict(sorted(out.items()))


def run_bench(
    seeds: list[int],
    *,
    mode: str | None,
    hours: float,
    warmup_min: float,
    overrides: dict[str, Any] | None = None,
    progress: Any = None,
) -> dict[str, Any]:
    from service.modelload import ModelRef, load_model

    settings = identmode.bench_settings(mode, overrides)
    model = load_model(ModelRef.from_settings(settings))
    started = time.perf_counter()
    results = []
    for seed in seeds:
        results.append(run_seed(model, settings, seed, hours=hours, warmup_min=warmup_min))
        if progress is not None:
            r = results[-1]
            progress(
                f"seed {seed}: fresh {np.mean(r.fresh) if r.fresh else 0:.3f}, "
                f"gap {longest_gap(r.fresh)} min, "
                f"{r.fits} fits ({time.perf_counter() - started:.0f} s)"
            )
    return {
        "synthetic": True,
        "mode": settings.identification.mode,
        "settings": overrides or {},
        "hours": hours,
        "warmup_min": warmup_min,
        "rom_rank": int(model.rom.rank),
        "seeds": len(seeds),
        **summarise(results),
        "wall_s": round(time.perf_counter() - started, 1),
    }


def _fmt(values: list[float | None], spec: str) -> str:
    return "".join("      –" if v is None else f"{v:{spec}}" for v in values)


def _print_table(out: dict[str, Any]) -> None:
    print(
        f"duty cycle ({out['hours']} h), mode {out['mode']}, {out['seeds']} seeds, reduced model rank "
        f"{out['rom_rank']}; synthetic data; wall {out['wall_s']} s"
    )
    print(
        f"fresh H at {100 * out['fresh_fraction']:.1f} % of the minutes after the first "
        f"{out['warmup_min']:.0f} "
        f"(worst seed {100 * out['fresh_fraction_min_seed']:.1f} %); longest gap {out['longest_gap_min']} min"
    )
    print(f"minutes not fresh, by reason: {out['not_fresh_minutes']}")
    print(f"{'':26}" + "".join(f"{'H' + str(i + 1):>7}" for i in range(7)))
    print(f"{'|error| % median (fresh)':26}{_fmt(out['h_err_pct_median'], '7.1f')}")
    print(f"{'|error| % p90':26}{_fmt(out['h_err_pct_p90'], '7.1f')}")
    print(f"{'CI coverage':26}{_fmt(out['coverage'], '7.2f')}")
    print(f"{'identified (CI narrow)':26}{_fmt(out['identified_fraction'], '7.2f')}")
    print(
        f"identification: {out['fits_per_seed']} per seed, wall median {out['identify_wall_s_median']} s, "
        f"p90 {out['identify_wall_s_p90']} s, max {out['identify_wall_s_max']} s; model runs median "
        f"{out['model_runs_median']}, max {out['model_runs_max']}"
    )
    if out["mode"] == IdentificationMode.COMBINED:
        print(
            f"per-condition identifications (combined mode): {out['per_condition_fits_per_seed']} per seed, "
            f"wall median {out['per_condition_wall_s_median']} s, max {out['per_condition_wall_s_max']} s; "
            f"served {100 * out['per_condition_served_fraction']:.1f} % of the fresh minutes"
        )


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1 or args.hours <= 0.25:
        print("error: --seeds must be >= 1 and --hours > 0.25", file=sys.stderr)
        return 2
    try:
        overrides = identmode.parse_sets(args.set)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        out = run_bench(
            seeds,
            mode=args.ident_mode,
            hours=args.hours,
            warmup_min=args.warmup_min,
            overrides=overrides,
            progress=progress_to_stderr,
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return report(out, as_json=args.json, table=_print_table)
