"""``python -m benchmarks restart``: the service's answers after a restart on a warm spindle (issue 16).

Data are SYNTHETIC: per seed the virtual plant (finer mesh, its own truth ``model.plant.h_true``, σ = 0.15 °C,
default settings) runs the issue's profile from a cold spindle: 5 min idle, 3000 rpm 60 min, 4000 rpm 45
min, 5000 rpm 45 min. The service sees the samples from minute S on (S = 0, 30, 60, 90: a restart after an
update, a power cut, a crash) and starts with no stored state (with ``--stored-offsets``: only the offset
calibration that the minute-0 run took in the idle first 5 min, as ``service.store.calibrations`` restores it
from the database). Per start and condition it reports, over the seeds, for the condition's last served
identification: the median |H error| per H against the plant's truth, the CI coverage per H, the fraction of
seeds whose CIs cover all seven, the median relative 95 % CI half-width per H (a covering CI is only useful if
it is narrow); for S > 0 also each H's median |error| as a multiple of the minute-0 start's (the issue's bar:
≤ 1.5). Per start: the minutes from the start to the first served H (the first successful identification's
window end on the samples' clock; median and maximum over the seeds; offline the job takes no sample time, in
the service add its wall time, ~0.2–1 s) and what that first H is worth (``first``: its coverage, median CI
half-width and the fraction of seeds in which each H is flagged identified, CI within
``identification.ci_rel_threshold`` and not at a bound; and the minutes to the first result with at least one
H identified, with the fraction of seeds that had one; core path).

Identification mode (``--mode per_condition|speed_map|combined``, ``--set KEY=VALUE``:
``benchmarks.identmode``; default the settings' ``identification.mode``), reported as ``mode``; core path
only (``--path filter`` is the per-condition protocol by construction). In combined mode each condition's
served H is its per-condition identification once there is one (``identmode.served_in_order``).

Paths (``--path``; ``--mode core|filter`` is accepted as its old spelling):

- ``core`` (default): the samples go through the service's own core offline
  (``service.core.offline.run_offline``, as ``chtc identify`` and ``python -m benchmarks chain``): whatever
  the service does today;
- ``filter``: what wiring the filtered live state would give, without the core: the samples are pushed
  through ``service.estimate.state.FilteredState`` (Schmidt–Kalman filter, wide "heated" prior at the
  start) and each identification window (the settings' schedule, 7, 20, 40, 60 min, counted from the
  speed change or, after a restart, from the filter's convergence) starts from the filtered snapshot at
  max(condition start, convergence time) with its covariance as ``start_cov``
  (``model.identify``; ``--start-modes K`` also fits the start's K leading uncertain directions with their
  Gaussian prior). H: 50 W/(m²·K) each until the first identification (considered error 100 %), then the
  newest result (as the core) with its CI's σ(log H) as the filter's considered H error. Offsets: a
  baseline over the first 5 min when the start is at minute 0 (spindle idle and cold), else unknown (the
  settings' ``offset_sd_c`` carried in the CIs); with ``--stored-offsets`` that baseline survives the
  restart (a calibration kept in the database).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from benchmarks import identmode
from benchmarks.restart_profile import (
    BASELINE_SAMPLES,
    DT_S,
    PROFILE,
    T0,
    Served,
    plant_run,
    truth,
)
from benchmarks.targets import progress_to_stderr, report
from service.contracts.mode import IdentificationMode

STARTS_MIN = (0, 30, 60, 90)
PATHS = ("core", "filter")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks restart``."""
    parser.add_argument("--seeds", type=int, default=5, help="virtual-plant noise seeds (default 5)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (split a long run), default 0")
    parser.add_argument(
        "--starts", type=int, nargs="+", default=list(STARTS_MIN), help="start minutes (default 0 30 60 90)"
    )
    parser.add_argument("--path", choices=PATHS, default=None, help="core (default) or filter: see above")
    identmode.add_arguments(parser, extra=PATHS, note="; core/filter: the old spelling of --path")
    parser.add_argument(
        "--start-modes", type=int, default=0, help="--path filter: start directions fitted in identify (0)"
    )
    parser.add_argument(
        "--stored-offsets",
        action="store_true",
        help="the minute-0 offset baseline survives the restart (a calibration stored in the database)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def stored_calibration(model: Any, settings: Any, run: Any) -> Any:
    """The offset baseline the service takes in the profile's idle, cold first 5 min (the core over those
    samples and the first ones at speed: the baseline ends with the rest): what the database holds after a
    run from minute 0 (``service.store.calibrations``; None: no baseline)."""
    from service.core.offline import run_offline
    from service.host.runtime import core_config
    from simulator.plantsamples import samples_from_plant

    samples = samples_from_plant(run, t0_s=T0)[: BASELINE_SAMPLES + 6]
    return run_offline(samples, model=model, config=core_config(settings)).calibration


def run_core(model: Any, settings: Any, run: Any, start: int, *, calibration: Any = None) -> list[Served]:
    """The service's core offline over the samples from index ``start`` on; ``calibration`` the stored
    offset baseline it restores (None: none)."""
    from service.core.config import Restored
    from service.core.offline import run_offline
    from service.host.runtime import core_config
    from simulator.plantsamples import samples_from_plant

    samples = samples_from_plant(run, t0_s=T0)[start:]
    restored = None if calibration is None else Restored(calibration=calibration)
    result = run_offline(samples, model=model, config=core_config(settings), restored=restored)
    out = []
    for rec in identmode.served_in_order(result.records):  # oldest first; combined mode: the held one
        speed = float(round(rec.condition.speed_rpm, -2))
        end = rec.window_to.timestamp() - T0
        h, lo, hi = (np.asarray(a, dtype=float) for a in (rec.h, rec.ci95_lo, rec.ci95_hi))
        ident = np.asarray(rec.identified, dtype=bool)
        out.append(Served(speed_rpm=speed, h=h, lo=lo, hi=hi, end_s=end, identified=ident))
    return out


def run_filter(
    model: Any, settings: Any, run: Any, start: int, *, seed: int, start_modes: int, stored_offsets: bool
) -> list[Served]:
    """The filtered live state and ``model.identify`` directly (module docstring, ``filter``)."""
    from benchmarks.restart_filter import FilterRestart

    runner = FilterRestart(
        model, settings, run, seed=seed, start_modes=start_modes, stored_offsets=stored_offsets
    )
    return runner.run(start)


def summarise(served: list[list[Served]], start_s: float) -> dict[str, Any]:
    """Per condition over the seeds (each seed's list of served results): the last result's figures."""
    conditions = []
    for _, speed, _, _ in PROFILE[1:]:
        h_true = truth(speed)
        rows = []
        for seed_served in served:
            last = [s for s in seed_served if s.speed_rpm == speed]
            if last:
                s = last[-1]
                rows.append(((s.h - h_true) / h_true, (s.lo <= h_true) & (h_true <= s.hi), _half_width(s)))
        if not rows:
            conditions.append({"speed_rpm": speed, "seeds_served": 0})
            continue
        err, cov, half = (np.array([r[i] for r in rows]) for i in range(3))
        conditions.append(
            {
                "speed_rpm": speed,
                "seeds_served": len(rows),
                "coverage": np.round(cov.mean(axis=0), 2).tolist(),
                "h_err_pct_median": np.round(100 * np.median(np.abs(err), axis=0), 1).tolist(),
                "covers_all": round(float(np.mean(cov.all(axis=1))), 2),
                "ci_half_width_pct_median": np.round(100 * np.median(half, axis=0), 0).tolist(),
            }
        )
    firsts = [min(seed_served, key=lambda s: s.end_s) for seed_served in served if seed_served]
    if not firsts:
        return {
            "first_served_min": None,
            "first_served_min_max": None,
            "first": None,
            "conditions": conditions,
        }
    minutes = [(s.end_s - start_s) / 60.0 for s in firsts]
    return {
        "first_served_min": round(float(np.median(minutes)), 1),
        "first_served_min_max": round(float(np.max(minutes)), 1),
        "first": _first_figures(firsts) | _first_identified(served, start_s),
        "conditions": conditions,
    }


def _first_identified(served: list[list[Served]], start_s: float) -> dict[str, Any]:
    """Minutes from the start to the first served result with at least one H flagged identified (median over
    the seeds that had one) and the fraction of seeds that had one (core path; {} without flags)."""
    if not any(s.identified is not None for seed_served in served for s in seed_served):
        return {}
    times = []
    for seed_served in served:
        hits = [s.end_s for s in seed_served if s.identified is not None and bool(s.identified.any())]
        if hits:
            times.append((min(hits) - start_s) / 60.0)
    return {
        "first_identified_min": round(float(np.median(times)), 1) if times else None,
        "first_identified_seeds": round(len(times) / len(served), 2),
    }


def _half_width(s: Served) -> np.ndarray:
    """The relative 95 % CI half-width (7,) of a result; an undefined one (a degenerate CI) is unbounded."""
    with np.errstate(invalid="ignore", over="ignore"):
        half = (s.hi - s.lo) / 2 / s.h
    return np.where(np.isnan(half), np.inf, half)


def _first_figures(firsts: list[Served]) -> dict[str, Any]:
    """What the first served H is worth, over the seeds: coverage, median CI half-width [%] and the fraction
    flagged identified, per H."""
    cov, half = [], []
    for s in firsts:
        h_true = truth(s.speed_rpm)
        cov.append((s.lo <= h_true) & (h_true <= s.hi))
        half.append(_half_width(s))
    out: dict[str, Any] = {
        "speeds_rpm": sorted({s.speed_rpm for s in firsts}),
        "coverage": np.round(np.mean(cov, axis=0), 2).tolist(),
        "ci_half_width_pct_median": np.round(100 * np.median(half, axis=0), 0).tolist(),
    }
    flags = [s.identified for s in firsts if s.identified is not None]
    if flags:
        out["identified_frac"] = np.round(np.mean(flags, axis=0), 2).tolist()
    return out


def add_ratios(starts: list[dict[str, Any]]) -> None:
    """Each H's median |error| as a multiple of the minute-0 start's at the same condition (starts > 0)."""
    base = next((s for s in starts if s["start_min"] == 0), None)
    if base is None:
        return
    ref = {c["speed_rpm"]: c.get("h_err_pct_median") for c in base["conditions"]}
    for s in starts:
        if s["start_min"] == 0:
            continue
        for c in s["conditions"]:
            r0 = ref.get(c["speed_rpm"])
            if r0 and c.get("h_err_pct_median"):
                c["h_err_ratio_vs_start0"] = [
                    round(e / max(b, 0.1), 1) for e, b in zip(c["h_err_pct_median"], r0, strict=True)
                ]


def run_bench(
    seeds: list[int],
    starts_min: list[int],
    *,
    path: str = "core",
    ident_mode: str | None = None,
    overrides: dict[str, Any] | None = None,
    start_modes: int = 0,
    stored_offsets: bool = False,
    progress: Any = None,
) -> dict[str, Any]:
    """``ident_mode`` None: the settings' ``identification.mode``; ``overrides``: ``--set`` settings."""
    from service.modelload import ModelRef, load_model

    settings = identmode.bench_settings(ident_mode, overrides)
    per_condition = IdentificationMode.PER_CONDITION
    mode = per_condition if path == "filter" else settings.identification.mode
    if path == "filter" and settings.identification.mode is not per_condition and ident_mode is not None:
        raise ValueError("--path filter runs the per-condition protocol only (no --mode speed_map)")
    model = load_model(ModelRef.from_settings(settings))
    started = time.perf_counter()
    served: dict[int, list[list[Served]]] = {s: [] for s in starts_min}
    for seed in seeds:
        run = plant_run(seed)
        cal = stored_calibration(model, settings, run) if path == "core" and stored_offsets else None
        for s_min in starts_min:
            idx = round(s_min * 60.0 / DT_S)
            if path == "core":  # the minute-0 run takes its own baseline; a restart restores it
                served[s_min].append(run_core(model, settings, run, idx, calibration=cal if idx else None))
            else:
                served[s_min].append(
                    run_filter(
                        model,
                        settings,
                        run,
                        idx,
                        seed=seed,
                        start_modes=start_modes,
                        stored_offsets=stored_offsets,
                    )
                )
        if progress is not None:
            progress(f"seed {seed} done ({time.perf_counter() - started:.0f} s)")
    starts = [{"start_min": s_min} | summarise(served[s_min], s_min * 60.0) for s_min in starts_min]
    add_ratios(starts)
    return {
        "synthetic": True,
        "mode": mode,
        "path": path,
        "settings": overrides or {},
        "start_modes": start_modes if path == "filter" else None,
        "stored_offsets": stored_offsets,
        "rom_rank": int(model.rom.rank),
        "seeds": len(seeds),
        "starts": starts,
        "wall_s": round(time.perf_counter() - started, 1),
    }


def _fmt(values: list[float] | None, spec: str) -> str:
    return "".join(f"{v:{spec}}" for v in values) if values else "   –"


def _print_table(out: dict[str, Any]) -> None:
    print(
        f"restart on a warm spindle, {out['mode']} ({out['path']}), {out['seeds']} seeds, reduced model rank "
        f"{out['rom_rank']}; last served H per condition; synthetic data; wall {out['wall_s']} s"
    )
    head = "".join(f"{'H' + str(i + 1):>7}" for i in range(7))
    for s in out["starts"]:
        print(
            f"\nstart at minute {s['start_min']}: first served H after {s['first_served_min']} min "
            f"(max {s.get('first_served_min_max')})"
        )
        first = s.get("first")
        if first:
            print(f"{'first H':20}{'coverage':>14}{_fmt(first.get('coverage'), '7.2f')}")
            print(f"{'':20}{'CI half-width %':>14}{_fmt(first.get('ci_half_width_pct_median'), '7.0f')}")
            if "identified_frac" in first:
                print(f"{'':20}{'identified':>14}{_fmt(first['identified_frac'], '7.2f')}")
            if "first_identified_min" in first:
                print(
                    f"first result with an H identified after {first['first_identified_min']} min "
                    f"({first['first_identified_seeds']:.0%} of the seeds)"
                )
        print(f"{'':34}{head}")
        for c in s["conditions"]:
            tag = f"{c['speed_rpm']:.0f} rpm ({c['seeds_served']} seeds)"
            print(f"{tag:20}{'|error| % median':>14}{_fmt(c.get('h_err_pct_median'), '7.1f')}")
            print(f"{'':20}{'coverage':>14}{_fmt(c.get('coverage'), '7.2f')}  all 7: {c.get('covers_all')}")
            print(f"{'':20}{'CI half-width %':>14}{_fmt(c.get('ci_half_width_pct_median'), '7.0f')}")
            if "h_err_ratio_vs_start0" in c:
                print(f"{'':20}{'× start 0':>14}{_fmt(c['h_err_ratio_vs_start0'], '7.1f')}")


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1 or args.start_modes < 0:
        print("error: --seeds must be >= 1 and --start-modes >= 0", file=sys.stderr)
        return 2
    bad = [s for s in args.starts if not 0 <= s < sum(p[0] for p in PROFILE) / 60.0 - 10.0]
    if bad:
        print(f"error: --starts: {bad} outside the profile (0 to its end minus 10 min)", file=sys.stderr)
        return 2
    path, ident_mode = args.path, args.ident_mode
    if ident_mode in PATHS:  # the old spelling of --path
        if path is not None and path != ident_mode:
            print(f"error: --mode {ident_mode} contradicts --path {path}", file=sys.stderr)
            return 2
        path, ident_mode = ident_mode, None
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        out = run_bench(
            seeds,
            list(args.starts),
            path=path or "core",
            ident_mode=ident_mode,
            overrides=identmode.parse_sets(args.set),
            start_modes=args.start_modes,
            stored_offsets=args.stored_offsets,
            progress=progress_to_stderr,
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return report(out, as_json=args.json, table=_print_table)
