"""``chtc identify``: offline, deterministic identification of H1-H7 from recorded log files.

The log's samples go through the service's own core (detector, scheduler, live state, windows) with every
identification run inline with the configured seed (``experimental.seed``, ``--seed``): the same files
always give the same H. Prints one line per identification with H and its 95 % confidence intervals, and
writes them as JSON with ``--json FILE`` (``-`` for stdout), each with ``growth``: the thermal growth at the
spindle nose at the identification's end as ``/compensation`` would have served it (axial, radial and the
steady axial growth in µm, their 0.1-µm integers and 95 % CIs, over the zero (``compensation.reference_c``,
else the provisional one: the first converged live field's); ``service.shell.growthserve.GrowthHistory``;
null for an identification that did not succeed).

The log is sampled as the live acquisition samples it in ``chtc replay`` (one sample per
``acquisition.sample_period_s``; ``drivers.logsamples``), so both commands fit the same data. Without a
CAN
log the speed and torque must be stated (``--speed-rpm``/``--torque-nm``, constant over the log). Exit status:
0 when at least one identification succeeded; 1 when none did, with the reason on stderr (each condition's
length against what an identification needs, or why no condition was detected); 2 for unusable input.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.commands._common import check_log_arguments
from service.contracts.mode import IdentificationMode
from service.core.jobbook import MAP_METHOD
from service.serve.numbers import format_bound

if TYPE_CHECKING:
    from service.contracts.calibration import Calibration
    from service.contracts.growth import GrowthEstimate, GrowthValue
    from service.contracts.snapshots import IdentificationRecord
    from service.core.offline import OfflineResult
    from service.settings import IdentificationSettings, Settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="temperature CSV (chtc record / drivers.logs format)")
    parser.add_argument(
        "can", type=Path, nargs="?", default=None, help="CAN log (.blf/.asc/.log/.csv/.trc/.mf4)"
    )
    parser.add_argument(
        "--config", type=Path, default=None, help="settings TOML (default: built-in defaults)"
    )
    parser.add_argument(
        "--speed-rpm",
        type=float,
        default=None,
        help="without a CAN log: the spindle speed, constant over the whole log (default: from the CAN log)",
    )
    parser.add_argument(
        "--torque-nm",
        type=float,
        default=None,
        help="without a CAN log: the spindle torque, constant (default: from the CAN log)",
    )
    parser.add_argument("--seed", type=int, default=None, help="rng seed (default experimental.seed)")
    parser.add_argument("--method", default=None, help="identification method (default experimental.method)")
    parser.add_argument(
        "--json",
        dest="json_out",
        default=None,
        help="write the identifications as JSON to this file, - for stdout (default: no JSON)",
    )


def num(x: float | None) -> float | None:
    """A JSON/CSV number: None for None and NaN, else rounded to 6 decimals."""
    return None if x is None or x != x else round(float(x), 6)


def record_dict(r: IdentificationRecord) -> dict[str, object]:
    """One identification as plain JSON (units in the keys, UTC ISO-8601 times)."""
    return {
        "id": r.id,
        "outcome": r.outcome,
        "reason": r.reason,
        "message": r.message,
        "condition": {
            "id": r.condition.id,
            "speed_rpm": num(r.condition.speed_rpm),
            "torque_nm": num(r.condition.torque_nm),
            "ambient_c": num(r.condition.ambient_c),
            "since": r.condition.since.isoformat(),
        },
        "window_from": r.window_from.isoformat(),
        "window_to": r.window_to.isoformat(),
        "h_w_m2k": [num(x) for x in r.h],
        "ci95_lo_w_m2k": [num(x) for x in r.ci95_lo],
        "ci95_hi_w_m2k": [num(x) for x in r.ci95_hi],
        "identified": [bool(x) for x in r.identified],
        "prior_dominated": [bool(x) for x in getattr(r, "prior_dominated", [False] * len(r.h))],
        "f_c2": num(r.f),
        "fit": num(r.fit),
        "rmse_c": num(r.rmse_c),
        "method": r.method,
        "model_version": r.model_version,
    }


def _growth_value(v: GrowthValue) -> dict[str, object]:
    return {
        "um": num(v.um),
        "plc_0p1um": v.plc_0p1um,
        "ci95_um": [num(v.ci95_um[0]), num(v.ci95_um[1])],
    }


def growth_dict(g: GrowthEstimate | None) -> dict[str, object] | None:
    """The growth at an identification's end as ``/compensation`` would have served it (None: none)."""
    if g is None:
        return None
    return {
        "at": g.at.isoformat(),
        "t_ref_c": num(g.t_ref_c),
        "axial": _growth_value(g.axial),
        "radial": _growth_value(g.radial),
        "steady_axial": _growth_value(g.forecast.steady_axial),
    }


def fit_status(r: IdentificationRecord) -> str:
    """What a line's status says: the outcome unless it is ``ok``; then how many H are identified (a CI
    narrow enough): ``ok 7/7 H``, ``partial 3/7 H`` or ``weak 0/7 H`` (a fit that ran but pins no H)."""
    if r.outcome != "ok":
        return str(r.outcome)
    n, total = sum(bool(x) for x in r.identified), len(r.identified)
    word = "ok" if n == total else "weak" if n == 0 else "partial"
    return f"{word} {n}/{total} H"


def fit_kind(r: IdentificationRecord) -> str:
    """``speed-map fit`` (one fit of H over every speed of its window; the line shows the map's H at the
    window's end) or ``per-condition fit`` (one H for the window at one condition)."""
    return "speed-map fit" if getattr(r, "method", None) == MAP_METHOD else "per-condition fit"


def format_record(r: IdentificationRecord, box: tuple[float, float] | None = None) -> str:
    """One identification as ``chtc identify`` prints it; CI bounds beyond the search ``box`` W/(m²·K) print
    as ``> high`` / ``< low`` (``service.serve.numbers.format_bound``), a prior-dominated H (a MAP fit's H
    the data did not see) is marked ``(prior)``."""
    at = "H at the window's end, " if fit_kind(r) == "speed-map fit" else ""
    head = (
        f"#{r.id} {fit_status(r):<13} {fit_kind(r):<17}  {at}condition {r.condition.id} "
        f"({r.condition.speed_rpm:.0f} rpm, {r.condition.ambient_c:.1f} °C) "
        f"window {r.window_from:%Y-%m-%dT%H:%M:%SZ} .. {r.window_to:%H:%M:%SZ}"
    )
    if r.outcome != "ok":
        return f"{head}\n    {r.message}"
    prior = getattr(r, "prior_dominated", None)
    prior = [False] * len(r.h) if prior is None else list(prior)
    zones = "  ".join(
        f"H{i + 1}={h:.1f} [{format_bound(lo, box)}, {format_bound(hi, box)}]"
        f"{'' if ok else '?'}{' (prior)' if p else ''}"
        for i, (h, lo, hi, ok, p) in enumerate(
            zip(r.h, r.ci95_lo, r.ci95_hi, r.identified, prior, strict=True)
        )
    )
    tail = f"fit {r.fit:.4f}, RMSE {r.rmse_c:.3f} °C"
    legend = "'?' = poorly identified, '(prior)' = not seen by the data: the prior's value and band"
    return f"{head}\n    W/(m²·K), 95 % CI ({legend}): {zones}\n    {tail}"


def summary_line(records: Sequence[IdentificationRecord]) -> str:
    """One line counting the lines by status, e.g. ``9 identifications: 0 ok (7/7 H), 3 partial, 6 weak``."""
    words = [fit_status(r).split()[0] for r in records]
    ok = [r for r in records if r.outcome == "ok"]
    parts = [
        f"{words.count('ok')} ok (7/7 H)",
        f"{words.count('partial')} partial",
        f"{words.count('weak')} weak",
    ]
    if len(ok) < len(records):
        parts.append(f"{len(records) - len(ok)} not ok")
    maps = sum(fit_kind(r) == "speed-map fit" for r in records)
    kinds = f"{maps} speed-map fits, {len(records) - maps} per-condition fits"
    return f"{len(records)} identifications: {', '.join(parts)}; {kinds}"


def explain_nothing(result: OfflineResult, settings: Settings, *, can_ok: int) -> list[str]:
    """Why a log gave no successful identification: per detected condition, how long it lasted against what an
    identification needs; or why no condition was detected (``can_ok``: samples with a fresh speed/torque)."""
    ident, exp = settings.identification, settings.experimental
    per_condition = ident.mode is IdentificationMode.PER_CONDITION
    if per_condition:
        need_s = max(ident.min_window_s, 60.0 * ident.schedule_min[0])
        need = (
            f"an identification needs {need_s / 60:.1f} min of data at one condition "
            f"(identification.min_window_s = {ident.min_window_s:g} s, first run "
            f"{ident.schedule_min[0]:g} min after the condition starts)"
        )
    else:
        need_s = 60.0 * exp.map_min_window_min
        need = (
            f"identification.mode = {ident.mode}: the first map fit needs {need_s / 60:.1f} min of data "
            "after the live state converged, at any speeds (experimental.map_min_window_min = "
            f"{exp.map_min_window_min:g})"
        )
    if result.samples == 0 or result.first is None or result.last is None:
        return ["the temperature log has no rows"]
    span_s = (result.last - result.first).total_seconds()
    lines = [
        f"the log covers {span_s / 60:.1f} min "
        f"({result.first:%Y-%m-%dT%H:%M:%SZ} .. {result.last:%H:%M:%SZ}); {need}"
    ]
    if not result.conditions:
        lines.append(
            f"no operating condition was detected: {can_ok} of {result.samples} samples had a fresh speed "
            "and torque (the CAN log is missing, does not cover the rows' times, or reports FAULT), "
            f"or the log is shorter than the detector's hold time (detector.hold_s = "
            f"{settings.detector.hold_s:g} s)"
        )
    ends = [c.since for c in result.conditions[1:]] + [result.last]
    for cond, end in zip(result.conditions, ends[: len(result.conditions)], strict=True):
        lasted_s = (end - cond.since).total_seconds()
        head = f"condition {cond.id} ({cond.speed_rpm:.0f} rpm, {cond.ambient_c:.1f} °C)"
        if abs(cond.speed_rpm) < 100.0:
            lines.append(
                f"{head}: spindle idle for {lasted_s / 60:.1f} min (no bearing heat: not identifiable)"
            )
        elif per_condition and lasted_s < need_s:
            lines.append(f"{head} lasted {lasted_s / 60:.1f} min: too short, {need_s / 60:.1f} min needed")
    if result.records:
        lines.append(
            f"{len(result.records)} identifications ran and none succeeded: see their messages above"
        )
    if span_s < need_s:
        lines.append(
            "a recording of a sped-up simulation stamped with wall time looks this short: record it with "
            "`chtc record --speedup` equal to the simulator's (docs/design/simulation.md)"
        )
    return lines


def offsets_line(calibration: Calibration | None, ident: IdentificationSettings) -> str:
    """What happened to the sensor offsets (service.acquire.calibration)."""
    if not ident.offset_calibration:
        return "sensor offsets: calibration off (measurements as recorded)"
    if calibration is None:
        return (
            "sensor offsets: no baseline (the log never rests at the ambient long enough); "
            f"their 1σ {ident.offset_sd_c:.3f} °C is carried in the CIs"
        )
    c = calibration
    return (
        f"sensor offsets: zeroed against a baseline at rest, {c.t_from.isoformat(timespec='seconds')} to "
        f"{c.t_to.isoformat(timespec='seconds')} ({c.samples} samples): {np.nanmin(c.offsets_c):+.3f} to "
        f"{np.nanmax(c.offsets_c):+.3f} °C, 1σ ≤ {np.max(c.sd_c):.3f} °C"
    )


def main(args: argparse.Namespace) -> int:
    from drivers.logs import LogFormatError, read_temperature_csv
    from drivers.logsamples import samples_from_logs
    from service.core.offline import run_offline
    from service.host.runtime import core_config
    from service.modelload import ModelRef, load_model
    from service.settings import SettingsError, load_settings

    try:
        settings = load_settings(args.config)
        check_log_arguments(args.csv, args.can)
        if args.can is None and args.speed_rpm is None:
            read_temperature_csv(args.csv)  # a broken file is reported first, with its line
            raise ValueError(
                "no CAN log: the speed and torque are unknown; give the CAN log recorded with the "
                "temperatures, or state a constant condition with --speed-rpm and --torque-nm"
            )
        data = samples_from_logs(
            args.csv,
            args.can,
            period_s=settings.acquisition.sample_period_s,
            speed_rpm=args.speed_rpm,
            torque_nm=args.torque_nm,
        )
    except (SettingsError, LogFormatError, OSError, ValueError) as err:
        print(f"chtc identify: {err}", file=sys.stderr)
        return 2
    exp = settings.experimental.model_copy(
        update={k: v for k, v in (("seed", args.seed), ("method", args.method)) if v is not None}
    )
    settings = settings.model_copy(update={"experimental": exp})
    model = load_model(ModelRef.from_settings(settings))
    growth = None
    if args.json_out is not None:  # the growth history (docs/design/growth.md): only for the JSON
        from service.shell.growthserve import GrowthHistory

        growth = GrowthHistory(model, t_ref_c=settings.compensation.reference_c)
    result = run_offline(data.samples, model=model, config=core_config(settings), on_sample=growth)
    source = (
        f"{data.frames} CAN frames ({data.bad_frames} undecodable)"
        if args.can is not None
        else f"stated {args.speed_rpm:g} rpm, {args.torque_nm:g} N·m"
    )
    print(
        f"{data.rows} rows -> {len(data.samples)} samples every {settings.acquisition.sample_period_s:g} s, "
        f"{source}; {len(result.records)} identifications "
        f"({settings.identification.mode}, seed {settings.experimental.seed})"
    )
    print(offsets_line(result.calibration, settings.identification))
    for r in result.records:
        print(format_record(r, model.ref.h_box))
    print(summary_line(result.records))
    if args.json_out is not None:
        by_id = growth.by_id if growth is not None else {}
        rows = [record_dict(r) | {"growth": growth_dict(by_id.get(r.id))} for r in result.records]
        text = json.dumps(rows, indent=2)
        if args.json_out == "-":
            print(text)
        else:
            Path(args.json_out).write_text(text + "\n", encoding="utf-8")
    if not any(r.outcome == "ok" for r in result.records):
        can_ok = sum(bool(x.can_ok) for x in data.samples)
        why = explain_nothing(result, settings, can_ok=can_ok)
        print("chtc identify: nothing identified: " + "\n  ".join(why), file=sys.stderr)
        return 1
    return 0
