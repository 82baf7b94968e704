"""``python -m benchmarks compensation``: what ``/compensation`` serves, minute by minute, against the plant's
truth (issue 26 item 10).

Data are SYNTHETIC, on duty cycles of the product's own making whose truth appears nowhere else: per seed a
random smooth H(speed) curve per zone (``simulator.randomtruth``, never ``model.plant.h_true``), the duty
cycle of ``simulator.duty`` (``--rest-min`` at rest, 30, then the speed changing every 1–6 min over 0–7000
rpm, torque 3–15 N·m, ambient drifting ±1 °C), the virtual plant on its own finer mesh and time step, run
clean and with per-channel offsets of ±0.2 °C, with its own mechanics (``--plant-mechanics drawn``, the
default: per seed a mount restraint between free and held and α factors within ±5 %, ``model.plantmech``; the
service keeps its TOML's; ``nominal``: the plant shares them, as before issue 27). Scenarios per seed
(``benchmarks.compensation_run``): the normal run (both variants), a warm restart half-way with the stored
state and one without, a 10-min DAQ outage with CAN alive, and 10 min with both devices down (offsets
variant). Every minute the bench reads ``SoftSensorService.compensation()`` and ``chtc()`` (what the API
serves) and compares the axial growth and its 95 % CI with the plant's true growth (over the plant's cold
uniform start: the controller zeroed cold) and each served H with the truth at the plant's speed then.

Figures (JSON keys), pooled over the seeds: ``usable_fraction`` (normal runs, minutes after the rest), the
``reasons`` when not usable, the axial |error| median / 95th percentile / max when usable, the CI coverage
when usable, ``rest_zero_covered`` (rest minutes whose served CI covers 0; a minute with nothing served
counts as not covered), ``h_coverage`` and ``flag_miss`` per H (fresh /chtc minutes of the normal runs after
the rest), the restarts', the outages' figures, ``max_ci_bound_over_box``; the issue's bars beside them.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks import identmode
from benchmarks.compensation_run import (
    PER_MIN,
    Minute,
    Plan,
    SeedRows,
    Tick,
    add_jobs_argument,
    add_plant_mechanics_argument,
    plan_for,
    run_seed,
)
from benchmarks.targets import Target, format_verdicts, progress_to_stderr, report, verdicts
from service.serve.controlled import ControlLimits, ControlState, step_control

NORMAL = ("normal_clean", "normal_offsets")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks compensation``."""
    parser.add_argument("--seeds", type=int, default=3, help="random truths and duty cycles (default 3)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (split a long run), default 0")
    parser.add_argument("--hours", type=float, default=2.5, help="profile length incl. the rest (2.5 h)")
    parser.add_argument("--rest-min", type=int, default=30, help="rest before machining, min (30)")
    add_jobs_argument(parser)
    add_plant_mechanics_argument(parser)
    identmode.add_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--ticks-out",
        default=None,
        help="also write every sample's served growth, CI and plain verdict per seed (pickle) to this file, "
        "to try CI gates and command settings offline (``benchmarks.compensation.control_grid``; "
        "default: none written)",
    )


def targets(settings: Any) -> tuple[Target, ...]:
    """The issue's bars; the tolerance bars only where the settings have a ``compensation`` section."""
    comp = getattr(settings, "compensation", None)
    out = [
        Target("usable_fraction", ">=", 0.90, note="normal runs, after the rest"),
        Target("err_um_median_usable", "<=", 0.5, unit="µm"),
        Target("err_um_p95_usable", "<=", 1.5, unit="µm"),
        Target("coverage_usable", "in", (0.90, 0.99)),
        Target("rest_zero_covered", ">=", 0.95),
        Target("restart_no_state.coverage_usable", ">=", 0.85),
        Target("restart_no_state.h_coverage_min", ">=", 0.85),
        Target("restart_no_state.flag_miss_max", "<=", 0.05),
        Target("restart_stored.err_um_max_after_converged", "<=", 1.0, unit="µm"),
        Target(
            "restart_stored.first_usable_min_worst",
            "<=",
            15.0,
            unit="min",
            note="worst seed; never usable: the minutes watched",
        ),
        Target("flag_miss_max", "<=", 0.05, note="per H, normal runs"),
        Target("outage_can_alive.coverage_usable", ">=", 0.85),
        Target("outage_can_alive.fresh_minutes", "<=", 0.0),
        Target("outage_both.usable_s_after_loss", "<=", 60.0, unit="s", note="worst seed"),
        Target("max_ci_bound_over_box", "<=", 10.0),
    ]
    ctl = getattr(settings, "controller", None)
    if comp is not None and ctl is not None:
        from service.core.config import control_limits

        limits = control_limits(settings)
        out += [
            Target("transitions_per_hour_median", "<=", 2.0, note="with the CI gate, median over runs"),
            Target("transitions_per_hour_max", "<=", 6.0, note="in any run's clock hour"),
            Target("gated.usable_fraction", ">=", 0.90, note="with the CI gate"),
            Target("gated.coverage_usable", "in", (0.90, 0.99), note="with the CI gate"),
            Target("command.err_um_p95", "<=", 1.5, unit="µm", note="every machining minute"),
            Target("command.max_step_um", "<=", limits.profile.max_step_um, unit="µm"),
            Target("command.sign_changes_at_verdict_change", "<=", 0.0),
        ]
    if comp is not None:
        # the served verdict has the CI gate (issue 42): a half-width above the tolerance stays usable for at
        # most ci_exit_hold_s, and never above ci_hard_fraction × the tolerance
        hard = float(comp.max_ci95_um) * float(getattr(comp, "ci_hard_fraction", 1.0))
        out.append(
            Target("ci_half_um_max_usable", "<=", hard, unit="µm", note="ci_hard_fraction × tolerance")
        )
        out.append(Target("outage_can_alive.usable_min", "<=", float(comp.max_open_loop_min), unit="min"))
    return tuple(out)


# ------------------------------------------------------------------------------------------------ figures


def _r(x: Any, nd: int = 3) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def growth_figures(rows: list[Minute]) -> dict[str, Any]:
    """Usable fraction, reasons, |error| and coverage when usable, over ``rows``."""
    usable = [m for m in rows if m.usable]
    err = np.array([abs(m.um - m.truth_um) for m in usable])
    covered = [m.lo <= m.truth_um <= m.hi for m in usable]
    half = [0.5 * (m.hi - m.lo) for m in usable]
    served = [m for m in rows if m.served]
    err_all = np.array([abs(m.um - m.truth_um) for m in served])
    z = np.array([(m.um - m.truth_um) / (0.5 * (m.hi - m.lo) / 1.959964) for m in served if m.hi > m.lo])
    reasons: dict[str, int] = {}
    for m in rows:
        if not m.usable:
            key = m.reason or m.status
            reasons[key] = reasons.get(key, 0) + 1
    return {
        "minutes": len(rows),
        "usable_fraction": _r(len(usable) / len(rows)) if rows else None,
        "reasons": dict(sorted(reasons.items())),
        "err_um_median_usable": _r(np.median(err)) if err.size else None,
        "err_um_p95_usable": _r(np.percentile(err, 95)) if err.size else None,
        "err_um_max_usable": _r(err.max()) if err.size else None,
        "coverage_usable": _r(np.mean(covered)) if covered else None,
        "ci_half_um_max_usable": _r(max(half)) if half else None,
        # every minute something was served, usable or not (the figures before the policy's verdict)
        "served_fraction": _r(len(served) / len(rows)) if rows else None,
        "err_um_median_served": _r(np.median(err_all)) if err_all.size else None,
        "err_um_max_served": _r(err_all.max()) if err_all.size else None,
        "coverage_served": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in served])) if served else None,
        # the growth's z-score (error / its 1σ) over the served minutes: mean (bias) and spread (1: honest)
        "growth_z_mean_served": _r(z.mean(), 2) if z.size else None,
        "growth_z_sd_served": _r(z.std(), 2) if z.size else None,
    }


def h_figures(rows: list[Minute]) -> dict[str, Any]:
    """Per H over the fresh /chtc minutes: CI coverage of the truth, and the fraction of ``identified`` flags
    whose CI misses it (None where no minute or no flag)."""
    fresh = [m for m in rows if m.h_fresh and m.h is not None]
    if not fresh:
        none = [None] * 7
        return {"h_minutes": 0, "h_coverage": none, "flag_miss": none, "h_z_mean": none, "h_z_sd": none}
    truth = np.array([m.h_truth for m in fresh])
    lo, hi = np.array([m.h_lo for m in fresh]), np.array([m.h_hi for m in fresh])
    cov = (lo <= truth) & (truth <= hi)
    flags = np.array([m.identified for m in fresh], dtype=bool)
    miss = [_r(np.mean(~cov[flags[:, i], i])) if flags[:, i].any() else None for i in range(7)]
    # z = ln(H / truth) / σ, σ the served band's in ln H (its half-width / 1.96; truncated bands read wider)
    z = np.log(np.array([m.h for m in fresh]) / truth) / (np.log(hi / lo) / (2.0 * 1.959964))
    return {
        "h_minutes": len(fresh),
        "h_coverage": [_r(c) for c in cov.mean(axis=0)],
        "flag_miss": miss,
        "h_z_mean": [_r(v, 2) for v in z.mean(axis=0)],
        "h_z_sd": [_r(v, 2) for v in z.std(axis=0)],
    }


def _max_or_none(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return max(vals) if vals else None


def _min_or_none(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return min(vals) if vals else None


def rest_figures(rows: list[Minute], plan: Plan) -> dict[str, Any]:
    """Rest minutes (after minute 0, before machining): served CI covering the true growth 0."""
    rest = [m for m in rows if 0 < m.t_s < 60.0 * plan.rest_min]
    return {
        "rest_zero_covered": _r(np.mean([m.served and m.lo <= 0.0 <= m.hi for m in rest])) if rest else None,
        "rest_served_fraction": _r(np.mean([m.served for m in rest])) if rest else None,
        "rest_truth_um_max": _r(max(abs(m.truth_um) for m in rest)) if rest else None,
    }


def restart_stored_figures(seed: SeedRows, plan: Plan) -> dict[str, Any]:
    """After the restart with the stored state: the largest gap to the uninterrupted run's served growth from
    the first converged minute on, the minutes to the first usable one, whether the reference was kept."""
    base = {round(m.t_s): m for m in seed.rows["normal_offsets"]}
    rows = seed.rows["restart_stored"]
    conv = next((i for i, m in enumerate(rows) if m.converged), None)
    gaps = [
        abs(m.um - base[round(m.t_s)].um)
        for m in rows[conv or 0 :]
        if conv is not None and m.served and base[round(m.t_s)].served
    ]
    first = next((m.t_s / 60.0 - plan.restart_min for m in rows if m.usable), None)
    usable = [m for m in rows if m.usable]
    refs = [m.t_ref_c for m in rows if m.served]
    before = np.nan if seed.ref_before_restart is None else seed.ref_before_restart
    return {
        "err_um_max_after_converged": _r(max(gaps)) if gaps else None,
        "first_usable_min": _r(first, 1),
        "reference_kept": None if not refs else bool(np.max(np.abs(np.array(refs) - before)) <= 1e-6),
        # against the truth too: a gap to the uninterrupted run may be either run's error
        "coverage_usable": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in usable])) if usable else None,
        "err_um_max_usable": _r(max(abs(m.um - m.truth_um) for m in usable)) if usable else None,
    }


def _outage(rows: list[Minute], span: tuple[int, int]) -> list[Minute]:
    return [m for m in rows if span[0] * 60.0 <= m.t_s < span[1] * 60.0]


def outage_figures(seed: SeedRows, plan: Plan) -> dict[str, Any]:
    """The DAQ outage with CAN alive (minutes inside it) and both down (10-s ticks after the last sample)."""
    daq = _outage(seed.rows["outages"], plan.daq_out)
    usable = [m for m in daq if m.usable]
    statuses: dict[str, int] = {}
    for m in daq:
        statuses[m.status] = statuses.get(m.status, 0) + 1
    after = [s for s, ok in seed.both_ticks if ok]
    return {
        "outage_can_alive": {
            "usable_min": len(usable),
            "coverage_usable": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in usable])) if usable else None,
            "fresh_minutes": sum(m.status == "fresh" for m in daq),
            "statuses": dict(sorted(statuses.items())),
        },
        "outage_both": {"usable_s_after_loss": max(after) if after else 0.0},
    }


def ci_bound_over_box(rows: list[Minute], box_hi: float) -> float | None:
    """The largest served H CI bound over the search box's upper bound."""
    his = [float(np.nanmax(m.h_hi)) for m in rows if m.h_hi is not None and np.isfinite(m.h_hi).any()]
    return _r(max(his) / box_hi, 4) if his else None


def seed_figures(seed: SeedRows, plan: Plan, box_hi: float) -> dict[str, Any]:
    """One seed's figures (also pooled by ``summarise``)."""
    normal = [m for name in NORMAL for m in seed.rows[name]]
    after = [m for m in normal if m.t_s >= 60.0 * plan.rest_min]
    no_state = seed.rows["restart_no_state"]
    first = next((i for i, m in enumerate(no_state) if m.usable), None)
    ns_served = [m for m in no_state[first or 0 :] if m.served] if first is not None else []
    return {
        **growth_figures(after),
        **h_figures(after),
        **rest_figures(normal, plan),
        "restart_stored": restart_stored_figures(seed, plan),
        "restart_no_state": {
            **growth_figures(no_state),
            **h_figures(no_state),
            "coverage_from_first_usable": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in ns_served]))
            if ns_served
            else None,
        },
        **outage_figures(seed, plan),
        "max_ci_bound_over_box": ci_bound_over_box([m for rows in seed.rows.values() for m in rows], box_hi),
        "plant_mechanics": seed.mechanics,
        "wall_s": round(seed.wall_s, 1),
    }


def summarise(
    seeds: dict[int, SeedRows], plan: Plan, box_hi: float, limits: ControlLimits | None = None
) -> dict[str, Any]:
    """Pooled figures over the seeds, and per seed; with ``limits``, the gated verdict and the command
    value (``control_figures``)."""
    per = {s: seed_figures(r, plan, box_hi) for s, r in seeds.items()}
    normal = [m for r in seeds.values() for name in NORMAL for m in r.rows[name]]
    after = [m for m in normal if m.t_s >= 60.0 * plan.rest_min]
    no_state = [m for r in seeds.values() for m in r.rows["restart_no_state"]]
    daq = [m for r in seeds.values() for m in _outage(r.rows["outages"], plan.daq_out)]
    usable_daq = [m for m in daq if m.usable]
    stored = [p["restart_stored"] for p in per.values()]
    stored_usable = [m for r in seeds.values() for m in r.rows["restart_stored"] if m.usable]
    ns = h_figures(no_state)
    pooled_h = h_figures(after)
    out: dict[str, Any] = {
        **growth_figures(after),
        **pooled_h,
        "flag_miss_max": _max_or_none(pooled_h["flag_miss"]),
        **rest_figures(normal, plan),
        "restart_stored": {
            "err_um_max_after_converged": _max_or_none([s["err_um_max_after_converged"] for s in stored]),
            "first_usable_min": None
            if any(s["first_usable_min"] is None for s in stored)
            else _max_or_none([s["first_usable_min"] for s in stored]),
            "first_usable_min_per_seed": [s["first_usable_min"] for s in stored],
            # for the bar: a seed never usable again counts as the minutes it was watched (a lower bound)
            "first_usable_min_worst": max(
                plan.total_min - plan.restart_min if s["first_usable_min"] is None else s["first_usable_min"]
                for s in stored
            ),
            "reference_kept": all(s["reference_kept"] for s in stored),
            "coverage_usable": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in stored_usable]))
            if stored_usable
            else None,
            "err_um_max_usable": _max_or_none([s["err_um_max_usable"] for s in stored]),
        },
        "restart_no_state": {
            **{k: v for k, v in growth_figures(no_state).items() if k != "minutes"},
            **ns,
            "h_coverage_min": _min_or_none(ns["h_coverage"]),
            "flag_miss_max": _max_or_none(ns["flag_miss"]),
        },
        "outage_can_alive": {
            "usable_min": max(p["outage_can_alive"]["usable_min"] for p in per.values()),
            "coverage_usable": _r(np.mean([m.lo <= m.truth_um <= m.hi for m in usable_daq]))
            if usable_daq
            else None,
            "fresh_minutes": sum(m.status == "fresh" for m in daq),
        },
        "outage_both": {
            "usable_s_after_loss": max(p["outage_both"]["usable_s_after_loss"] for p in per.values())
        },
        "max_ci_bound_over_box": _max_or_none([p["max_ci_bound_over_box"] for p in per.values()]),
        "wall_s_per_seed": [p["wall_s"] for p in per.values()],
        "per_seed": {str(s): p for s, p in per.items()},
    }
    if limits is not None:
        out |= control_figures({s: r.ticks for s, r in seeds.items()}, plan, limits)
    return out


# ------------------------------------------------------------------------ the CI gate and the command value


@dataclass(frozen=True, kw_only=True)
class Controlled:
    """One run's ticks through ``service.serve.controlled.step_control``: per tick the gated verdict and the
    command value [µm]."""

    ticks: list[Tick]
    usable: list[bool]
    command_um: list[float]


def control_run(ticks: list[Tick], limits: ControlLimits) -> Controlled:
    """The gate and the command over one run's ticks, exactly as the service steps them on each sample."""
    if not ticks:
        return Controlled(ticks=[], usable=[], command_um=[])
    state = ControlState.start(ticks[0].t)
    usable, command = [], []
    for tk in ticks:
        state, ok = step_control(
            state,
            t=tk.t,
            usable=tk.usable,
            reason=tk.reason,
            status=tk.status,
            growth_um=tk.um if tk.served else None,
            half_um=0.5 * (tk.hi - tk.lo) if tk.served else math.nan,
            limits=limits,
        )
        usable.append(ok)
        command.append(state.command.value_um)
    return Controlled(ticks=ticks, usable=usable, command_um=command)


def _transitions(flags: list[bool]) -> int:
    return sum(a != b for a, b in itertools.pairwise(flags))


def _hourly(run: Controlled, start_s: float, flags: list[bool]) -> tuple[float, int]:
    """Transitions per machining hour over the run after ``start_s``, and the most in one clock hour of it."""
    idx = [i for i, tk in enumerate(run.ticks) if tk.t_s >= start_s]
    if len(idx) < 2:
        return 0.0, 0
    hours = (run.ticks[idx[-1]].t_s - run.ticks[idx[0]].t_s) / 3600.0
    per_hour: dict[int, int] = {}
    for a, b in itertools.pairwise(idx):
        if flags[a] != flags[b]:
            h = int((run.ticks[b].t_s - start_s) // 3600.0)
            per_hour[h] = per_hour.get(h, 0) + 1
    total = sum(per_hour.values())
    return total / hours if hours > 0 else 0.0, max(per_hour.values(), default=0)


def control_figures(
    ticks: dict[int, dict[str, list[Tick]]], plan: Plan, limits: ControlLimits
) -> dict[str, Any]:
    """The verdict with the CI gate and the command value over the normal runs (machining, after the rest)
    and the outages run: transitions per machining hour (gated and plain), the gated usable fraction and
    coverage, the command's |error| against the truth on every machining minute, its largest step, and what
    it does where the verdict changes."""
    start_s = 60.0 * plan.rest_min
    rates, rates_plain, worst, worst_plain = [], [], [], []
    minutes: list[tuple[Tick, bool, float]] = []
    halves: list[float] = []
    steps: list[float] = []
    jumps: list[float] = []
    sign_changes = changes = 0
    outage_err: list[float] = []
    for runs in ticks.values():
        for name, run_ticks in runs.items():
            run = control_run(run_ticks, limits)
            cmd = run.command_um
            steps += [abs(b - a) for a, b in itertools.pairwise(cmd)]
            for i in range(1, len(cmd)):
                if run.usable[i] != run.usable[i - 1] and run.ticks[i].t_s >= start_s:
                    changes += 1
                    jumps.append(abs(cmd[i] - cmd[i - 1]))
                    if cmd[i] * cmd[i - 1] < 0.0:
                        sign_changes += 1
            if name == "outages":
                outage_err += [
                    abs(c - tk.truth_um)
                    for tk, c in zip(run.ticks, cmd, strict=True)
                    if tk.t_s >= start_s and math.isfinite(tk.truth_um)
                ]
                continue
            rate, most = _hourly(run, start_s, run.usable)
            rate_p, most_p = _hourly(run, start_s, [tk.usable for tk in run.ticks])
            rates.append(rate)
            worst.append(most)
            rates_plain.append(rate_p)
            worst_plain.append(most_p)
            for tk, ok, c in zip(run.ticks, run.usable, cmd, strict=True):
                if tk.t_s >= start_s and math.isfinite(tk.truth_um):
                    minutes.append((tk, ok, c))
                if ok and tk.t_s >= start_s:
                    halves.append(0.5 * (tk.hi - tk.lo))
    err = np.array([abs(c - tk.truth_um) for tk, _ok, c in minutes])
    usable = [tk for tk, ok, _c in minutes if ok]
    return {
        "transitions_per_hour_median": _r(np.median(rates)) if rates else None,
        "transitions_per_hour_max": max(worst, default=None),
        "transitions_per_hour_per_run": [_r(r, 2) for r in rates],
        "plain_transitions_per_hour_median": _r(np.median(rates_plain)) if rates_plain else None,
        "plain_transitions_per_hour_max": max(worst_plain, default=None),
        "gated": {
            "usable_fraction": _r(len(usable) / len(minutes)) if minutes else None,
            "coverage_usable": _r(np.mean([tk.lo <= tk.truth_um <= tk.hi for tk in usable]))
            if usable
            else None,
            "ci_half_um_max_usable": _r(max(halves)) if halves else None,
        },
        "command": {
            "err_um_median": _r(np.median(err)) if err.size else None,
            "err_um_p95": _r(np.percentile(err, 95)) if err.size else None,
            "err_um_max": _r(err.max()) if err.size else None,
            "max_step_um": _r(max(steps, default=0.0)),
            "verdict_changes": changes,
            "max_jump_um_at_verdict_change": _r(max(jumps, default=0.0)),
            "sign_changes_at_verdict_change": sign_changes,
            "outage_err_um_p95": _r(np.percentile(outage_err, 95)) if outage_err else None,
            "outage_err_um_max": _r(max(outage_err)) if outage_err else None,
        },
        "control": {
            "ci_enter_fraction": limits.gate.enter_fraction,
            "ci_exit_hold_s": limits.gate.exit_hold_s,
            "ci_hard_fraction": limits.gate.hard_fraction,
            "profile": limits.profile.name,
            "max_step_um": limits.profile.max_step_um,
            "max_rate_um_s": limits.profile.max_rate_um_s,
            "hold_s": limits.hold_s,
        },
    }


def control_grid(
    path: str,
    *,
    base: ControlLimits,
    enter: tuple[float, ...] = (0.6, 0.7, 0.8, 0.9, 1.0),
    exit_hold_s: tuple[float, ...] = (0.0, 60.0, 180.0, 300.0, 600.0),
    hard: tuple[float, ...] = (1.25, 1.5, 2.0),
    hold_s: tuple[float, ...] = (60.0, 120.0, 300.0),
) -> list[dict[str, Any]]:
    """The control figures for every combination of gate and hold settings over the ticks a run wrote with
    ``--ticks-out`` (the grid docs/design/policy.md reports)."""
    import pickle
    from dataclasses import replace

    with open(path, "rb") as fh:
        dumped = pickle.load(fh)
    out = []
    for e, x, h, hs in itertools.product(enter, exit_hold_s, hard, hold_s):
        gate = replace(base.gate, enter_fraction=e, exit_hold_s=x, hard_fraction=h)
        fig = control_figures(dumped["ticks"], dumped["plan"], replace(base, gate=gate, hold_s=hs))
        out.append(fig)
    return out


def _flat(out: dict[str, Any]) -> dict[str, float | None]:
    flat: dict[str, float | None] = {}
    for key, value in out.items():
        if isinstance(value, dict) and key != "per_seed":
            flat |= {f"{key}.{k}": v for k, v in value.items() if not isinstance(v, dict | list)}
        elif isinstance(value, int | float) and not isinstance(value, bool):
            flat[key] = value
    return flat


def run_bench(
    seeds: list[int],
    *,
    hours: float,
    rest_min: int = 30,
    mode: str | None = None,
    overrides: dict[str, Any] | None = None,
    progress: Any = None,
    jobs: int = 1,
    plant_mechanics: str = "drawn",
    ticks_out: str | None = None,
) -> dict[str, Any]:
    """The bench over ``seeds`` (module docstring), ``jobs`` seeds at a time in worker processes;
    ``ValueError`` for a bad option. ``ticks_out``: a file for every seed's per-sample ticks (pickle)."""
    from benchmarks.compensation_run import Plant
    from service.core.config import control_limits
    from service.modelload import ModelRef, load_model

    plan = plan_for(hours, rest_min=rest_min)
    settings = identmode.bench_settings(mode, overrides)
    model = load_model(ModelRef.from_settings(settings))
    started = time.perf_counter()
    results: dict[int, SeedRows] = {}

    def done(seed: int, rows: SeedRows) -> None:
        results[seed] = rows
        if progress is not None:
            progress(f"seed {seed} done: {rows.wall_s:.0f} s ({time.perf_counter() - started:.0f} s)")

    if jobs > 1 and len(seeds) > 1:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=min(jobs, len(seeds))) as pool:
            futures = {
                pool.submit(_seed_job, s, hours, rest_min, mode, overrides, plant_mechanics): s for s in seeds
            }
            for fut in as_completed(futures):
                done(futures[fut], fut.result())
        results = dict(sorted(results.items()))
    else:
        plant = Plant(model.spec, mechanics=plant_mechanics)
        for seed in seeds:
            done(seed, run_seed(model, settings, plant, seed, plan, progress=progress))
    if ticks_out is not None:
        import pickle

        with open(ticks_out, "wb") as fh:
            pickle.dump({"plan": plan, "ticks": {s: r.ticks for s, r in results.items()}}, fh)
    box_hi = float(model.ref.h_box[1])
    out: dict[str, Any] = {
        "synthetic": True,
        "mode": settings.identification.mode,
        "settings": overrides or {},
        "seeds": len(seeds),
        "seed_list": seeds,
        "plant_mechanics": plant_mechanics,
        "hours": hours,
        "plan_min": {
            "rest": plan.rest_min,
            "end": plan.total_min,
            "restart": plan.restart_min,
            "daq_outage": list(plan.daq_out),
            "both_down": list(plan.both_out),
        },
        "minute_samples": PER_MIN,
        "h_box": [float(model.ref.h_box[0]), box_hi],
        **summarise(results, plan, box_hi, control_limits(settings)),
    }
    out["targets"] = verdicts(targets(settings), _flat(out))
    out["wall_s"] = round(time.perf_counter() - started, 1)
    return out


def _seed_job(
    seed: int, hours: float, rest_min: int, mode: str | None, overrides: Any, plant_mechanics: str
) -> SeedRows:
    """One seed in a worker process (``--jobs``): its own model, plant and service; no progress lines."""
    from benchmarks.compensation_run import Plant
    from service.modelload import ModelRef, load_model

    settings = identmode.bench_settings(mode, overrides)
    model = load_model(ModelRef.from_settings(settings))
    plant = Plant(model.spec, mechanics=plant_mechanics)
    return run_seed(model, settings, plant, seed, plan_for(hours, rest_min=rest_min))


# ------------------------------------------------------------------------------------------------ output


def _h(values: list[float | None]) -> str:
    return "".join("      –" if v is None else f"{v:7.2f}" for v in values)


def _print_table(out: dict[str, Any]) -> None:
    p = out["plan_min"]
    print(
        f"served compensation vs the plant's truth (random H(speed) truths; synthetic), mode {out['mode']}, "
        f"{out['seeds']} seeds × {out['hours']} h; rest {p['rest']} min, restart at {p['restart']} min, "
        f"DAQ outage {p['daq_outage']} min, both down {p['both_down']} min; wall {out['wall_s']} s"
    )
    print(f"wall per seed [s]: {out['wall_s_per_seed']}")
    print(
        f"\nnormal runs (clean + offsets), {out['minutes']} minutes after the rest: usable "
        f"{out['usable_fraction']}"
    )
    print(f"  not usable, by reason [min]: {out['reasons']}")
    print(
        f"  when usable: axial |error| median {out['err_um_median_usable']} µm, "
        f"p95 {out['err_um_p95_usable']} µm, "
        f"max {out['err_um_max_usable']} µm; 95 % CI coverage {out['coverage_usable']}; "
        f"largest CI half-width {out['ci_half_um_max_usable']} µm"
    )
    print(
        f"  every minute served ({out['served_fraction']} of them), usable or not: axial |error| median "
        f"{out['err_um_median_served']} µm, max {out['err_um_max_served']} µm, "
        f"coverage {out['coverage_served']}"
    )
    print(
        f"  at rest (true growth 0): served CI covers 0 in {out['rest_zero_covered']} of the minutes "
        f"(something served in {out['rest_served_fraction']})"
    )
    print(f"{'':32}" + "".join(f"{'H' + str(i + 1):>7}" for i in range(7)))
    print(f"{'H CI coverage (fresh minutes)':32}{_h(out['h_coverage'])}")
    print(f"{'identified but missing':32}{_h(out['flag_miss'])}")
    print(f"{'z = ln(H/truth)/σ: mean':32}{_h(out['h_z_mean'])}")
    print(f"{'z: sd (1 = honest band)':32}{_h(out['h_z_sd'])}")
    print(
        f"  growth z over the served minutes: mean {out['growth_z_mean_served']}, "
        f"sd {out['growth_z_sd_served']}"
    )
    ns = out["restart_no_state"]
    print(
        f"\nwarm restart without stored state: usable {ns['usable_fraction']}, coverage when usable "
        f"{ns['coverage_usable']}, |error| median {ns['err_um_median_usable']} µm; reasons {ns['reasons']}"
    )
    print(f"{'H CI coverage':32}{_h(ns['h_coverage'])}")
    print(f"{'identified but missing':32}{_h(ns['flag_miss'])}")
    print(f"{'z: mean':32}{_h(ns['h_z_mean'])}")
    print(f"{'z: sd':32}{_h(ns['h_z_sd'])}")
    st = out["restart_stored"]
    print(
        f"warm restart with stored state: first usable after {st['first_usable_min_per_seed']} min; "
        f"largest gap to the uninterrupted run once converged {st['err_um_max_after_converged']} µm; "
        f"when usable: coverage {st['coverage_usable']}, largest error {st['err_um_max_usable']} µm; "
        f"reference kept: {st['reference_kept']}"
    )
    oc, ob = out["outage_can_alive"], out["outage_both"]
    print(
        f"DAQ outage, CAN alive: usable {oc['usable_min']} min (worst seed), coverage while usable "
        f"{oc['coverage_usable']}, minutes served as fresh {oc['fresh_minutes']}"
    )
    print(f"both devices down: usable up to {ob['usable_s_after_loss']} s after the last sample")
    print(f"largest served H CI bound / search box upper bound: {out['max_ci_bound_over_box']}")
    if "command" in out:
        g, c, k = out["gated"], out["command"], out["control"]
        print(
            f"\nwith the CI gate (enter {k['ci_enter_fraction']}, exit after {k['ci_exit_hold_s']} s, hard "
            f"{k['ci_hard_fraction']} × tolerance): transitions per machining hour median "
            f"{out['transitions_per_hour_median']}, most in an hour {out['transitions_per_hour_max']} (plain "
            f"verdict: {out['plain_transitions_per_hour_median']}, {out['plain_transitions_per_hour_max']}); "
            f"usable {g['usable_fraction']}, coverage when usable {g['coverage_usable']}"
        )
        print(
            f"command value ({k['profile']}, hold {k['hold_s']} s): |error| median {c['err_um_median']} µm, "
            f"p95 {c['err_um_p95']} µm, max {c['err_um_max']} µm; largest step {c['max_step_um']} µm; at "
            f"{c['verdict_changes']} verdict changes: largest jump {c['max_jump_um_at_verdict_change']} µm, "
            f"sign changes {c['sign_changes_at_verdict_change']}; outages: |error| p95 "
            f"{c['outage_err_um_p95']} µm"
        )
    print(format_verdicts(out["targets"]))


def main(args: argparse.Namespace) -> int:
    if args.seeds < 1 or args.jobs < 1:
        print("error: --seeds and --jobs must be >= 1", file=sys.stderr)
        return 2
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        out = run_bench(
            seeds,
            hours=float(args.hours),
            rest_min=int(args.rest_min),
            mode=args.ident_mode,
            overrides=identmode.parse_sets(args.set),
            progress=progress_to_stderr,
            jobs=int(args.jobs),
            plant_mechanics=str(args.plant_mechanics),
            ticks_out=args.ticks_out,
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return report(out, as_json=args.json, table=_print_table)
