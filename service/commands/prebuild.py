"""``chtc prebuild``: build the FE model and the reduced-model cache ahead of time.

The service needs the reduced model (``model.rom``) before it can identify anything; building it takes tens of
seconds on two cores, so container images (``deploy/Dockerfile``) and installs (``deploy/chtc.service``,
``ExecStartPre``) build it once. The cache file is keyed by geometry, mesh, rank and H box
(``model.rom_cache``), exactly as the running service computes it (``service.modelload.load_model``), so the
service later finds it and starts in seconds. Running it again is cheap: a hit only loads the file.

``--config`` is the service's settings TOML (environment ``CHTC_*`` applies as usual); ``--cache-dir``
overrides ``model.rom_cache_dir``. Prints what it built and where (``--json``: one JSON object).
Exit codes: 0 built or found, 1 bad settings or model error, 2 cache directory not writable.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

if TYPE_CHECKING:
    from service.settings import Settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``chtc prebuild``."""
    parser.add_argument(
        "--config", type=Path, default=None, help="settings TOML (default: built-in defaults)"
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="reduced-model cache directory (default: model.rom_cache_dir of the settings)",
    )
    parser.add_argument("--rebuild", action="store_true", help="rebuild even when the cache file exists")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def main(args: argparse.Namespace) -> int:
    """Run ``chtc prebuild``."""
    from service.settings import SettingsError, load_settings

    try:
        settings = load_settings(args.config)
    except SettingsError as err:
        print(f"chtc prebuild: {err}", file=sys.stderr)
        return 1
    cache_dir = Path(args.cache_dir) if args.cache_dir is not None else Path(settings.model.rom_cache_dir)
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"chtc prebuild: cache directory {cache_dir}: {err.strerror or err}", file=sys.stderr)
        return 2
    if not os.access(cache_dir, os.W_OK):
        print(f"chtc prebuild: cache directory {cache_dir}: not writable", file=sys.stderr)
        return 2
    try:
        report = build(settings, cache_dir, rebuild=args.rebuild, progress=_progress(args))
    except (ValueError, OSError) as err:  # model errors (SpindleError, RomError...) are ValueErrors
        print(f"chtc prebuild: {type(err).__name__}: {err}", file=sys.stderr)
        return 1
    print(json.dumps(report, indent=2) if args.json else format_report(report), flush=True)
    return 0


def _progress(args: argparse.Namespace) -> Callable[[str], None] | None:
    if args.quiet or args.json:
        return None
    return lambda text: print(f"  {text}", flush=True)


class PrebuildReport(TypedDict):
    """What :func:`build` did (printed as JSON with ``--json``)."""

    spindle: str
    fe_nodes: int
    fe_triangles: int
    fe_build_s: float
    rom_rank: int
    h_box_w_m2k: list[float]
    cache_key: str
    cache_file: str
    cache_bytes: int | None
    from_cache: bool
    rom_build_s: float
    total_s: float
    error_report: dict[str, bool | int | str | float]


def build(
    settings: Settings,
    cache_dir: Path,
    *,
    rebuild: bool = False,
    progress: Callable[[str], None] | None = None,
) -> PrebuildReport:
    """Build (or find) the FE model and reduced model for ``settings`` in ``cache_dir``; a report."""
    from model import rom_cache
    from model.fem import build_fe_model
    from model.geometry import load_spindle
    from model.rom import load_or_build_rom
    from service.modelload import ModelRef

    ref = ModelRef.from_settings(settings)
    started = time.perf_counter()
    spec = load_spindle(ref.spindle)
    fe = build_fe_model(spec, mesh_size_m=ref.mesh_size_m)
    fe_s = time.perf_counter() - started
    rom = load_or_build_rom(
        fe, spec, cache_dir, rank=ref.rom_rank, box=ref.h_box, rebuild=rebuild, progress=progress
    )
    path = rom_cache.cache_path(cache_dir, rom.key)
    return {
        "spindle": ref.spindle or "packaged model/data/spindle.toml",
        "fe_nodes": int(fe.n_nodes),
        "fe_triangles": len(fe.triangles),
        "fe_build_s": round(fe_s, 3),
        "rom_rank": int(rom.rank),
        "h_box_w_m2k": list(rom.h_box),
        "cache_key": rom.key,
        "cache_file": str(path.resolve()),
        "cache_bytes": path.stat().st_size if path.exists() else None,
        "from_cache": bool(rom.from_cache) and not rebuild,
        "rom_build_s": round(float(rom.build_s), 3),
        "total_s": round(time.perf_counter() - started, 3),
        "error_report": _scalars(rom.error_report),
    }


def _scalars(report: Mapping[str, object]) -> dict[str, bool | int | str | float]:
    """The JSON-friendly scalar entries of the reduced model's error report."""
    out: dict[str, bool | int | str | float] = {}
    for key, value in report.items():
        if isinstance(value, bool | int | str):
            out[key] = value
        elif isinstance(value, float):
            out[key] = round(value, 6)
    return out


def format_report(report: PrebuildReport) -> str:
    """A readable summary of :func:`build`'s report."""
    how = "found in cache" if report["from_cache"] else f"built in {report['rom_build_s']:.1f} s"
    lines = [
        f"FE model: {report['fe_nodes']} nodes, {report['fe_triangles']} triangles "
        f"({report['spindle']}, {report['fe_build_s']:.1f} s)",
        f"reduced model: rank {report['rom_rank']}, H box {report['h_box_w_m2k']} W/(m²·K), {how}",
        f"cache file: {report['cache_file']} ({report['cache_bytes']} bytes, key {report['cache_key'][:16]})",
    ]
    errors = {k: v for k, v in report["error_report"].items() if "err" in k or k.endswith("_c")}
    if errors:
        lines.append("reduced-model error vs full FE: " + ", ".join(f"{k}={v}" for k, v in errors.items()))
    lines.append(f"total {report['total_s']:.1f} s")
    return "\n".join(lines)
