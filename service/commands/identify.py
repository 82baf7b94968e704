"""``chtc identify``: offline, deterministic identification of H1-H7 from recorded log files.

The log's samples go through the service's own core (detector, scheduler, live state, windows) with every
identification run inline with the configured seed (``identification.seed``, ``--seed``): the same files
always give the same H. Prints one line per identification with H and its 95 % confidence intervals, and
writes them as JSON with ``--json FILE`` (``-`` for stdout).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="temperature CSV (chtc record / drivers.logs format)")
    parser.add_argument("can", type=Path, nargs="?", default=None, help="CAN log (.blf/.asc/.log/.csv)")
    parser.add_argument("--config", type=Path, default=None, help="settings TOML")
    parser.add_argument("--seed", type=int, default=None, help="rng seed (default identification.seed)")
    parser.add_argument(
        "--method", default=None, help="identification method (default identification.method)"
    )
    parser.add_argument(
        "--json", dest="json_out", default=None, help="write the identifications as JSON here"
    )


def record_dict(r: Any) -> dict[str, Any]:
    """One identification as plain JSON (units in the keys, UTC ISO-8601 times)."""

    def num(x: Any) -> float | None:
        return None if x is None or x != x else round(float(x), 6)

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
        "f_c2": num(r.f),
        "fit": num(r.fit),
        "rmse_c": num(r.rmse_c),
        "method": r.method,
        "model_version": r.model_version,
    }


def format_record(r: Any) -> str:
    head = (
        f"#{r.id} {r.outcome:<17} condition {r.condition.id} ({r.condition.speed_rpm:.0f} rpm, "
        f"{r.condition.ambient_c:.1f} °C) "
        f"window {r.window_from:%Y-%m-%dT%H:%M:%SZ} .. {r.window_to:%H:%M:%SZ}"
    )
    if r.outcome != "ok":
        return f"{head}\n    {r.message}"
    zones = "  ".join(
        f"H{i + 1}={h:.1f} [{lo:.1f}, {hi:.1f}]{'' if ok else '?'}"
        for i, (h, lo, hi, ok) in enumerate(zip(r.h, r.ci95_lo, r.ci95_hi, r.identified, strict=True))
    )
    tail = f"fit {r.fit:.4f}, RMSE {r.rmse_c:.3f} °C"
    return f"{head}\n    W/(m²·K), 95 % CI ('?' = poorly identified): {zones}\n    {tail}"


def offsets_line(calibration: Any, ident: Any) -> str:
    """What happened to the sensor offsets (service.calibration)."""
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
    from drivers.logs import LogFormatError
    from service.logsamples import samples_from_logs
    from service.modelload import ModelRef, load_model
    from service.offline import run_offline
    from service.runtime import core_config
    from service.settings import SettingsError, load_settings

    try:
        settings = load_settings(args.config)
        data = samples_from_logs(args.csv, args.can)
    except (SettingsError, LogFormatError, OSError) as err:
        print(f"chtc identify: {err}", file=sys.stderr)
        return 2
    ident = settings.identification.model_copy(
        update={k: v for k, v in (("seed", args.seed), ("method", args.method)) if v is not None}
    )
    settings = settings.model_copy(update={"identification": ident})
    model = load_model(ModelRef.from_settings(settings.model))
    result = run_offline(data.samples, model=model, config=core_config(settings))
    print(
        f"{data.rows} samples, {data.frames} CAN frames ({data.bad_frames} undecodable); "
        f"{len(result.records)} identifications (seed {settings.identification.seed})"
    )
    print(offsets_line(result.calibration, settings.identification))
    for r in result.records:
        print(format_record(r))
    if args.json_out is not None:
        text = json.dumps([record_dict(r) for r in result.records], indent=2)
        if args.json_out == "-":
            print(text)
        else:
            Path(args.json_out).write_text(text + "\n", encoding="utf-8")
    return 0
