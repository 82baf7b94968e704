"""``python -m benchmarks api``: GET /api/v1/chtc latency at a fixed rate, idle and while an identification
runs.

By default it measures the service users run (``benchmarks.api_live``: ``chtc demo`` at real rate and
×60, quiet and beside a CPU hog; issue 30). ``--served`` runs the earlier bench described below.

Set-up of ``--served`` (all on loopback):

- the API (REST outlet, ``api.outlet``) runs under uvicorn in a **subprocess**, one worker, around the real
  service (``simulator.served``: the core and the shell on SQLite, fed a virtual-plant run, a new sample
  every ``--field-period`` s; no devices and no worker process run beside it);
- the load is open-loop: ``--rate`` requests/s spread over ``--clients`` concurrent clients (one keep-alive
  connection each), each request sent at its scheduled instant; latency is measured at the client from send
  to full body; ``late_ms_p99`` says how far behind schedule sends were (client saturation). Two client kinds
  run alternately in the same invocation: a minimal asyncio-streams HTTP/1.1 client (``raw``, the headline
  ``chtc_*`` figures: it measures the server) and ``httpx.AsyncClient`` (``httpx_*``: it adds about 1 ms of
  client CPU per request, which at 200 req/s on a busy 2-core machine saturates the client itself);
- "busy" repeats the same load while a CPU-bound identification loop runs in a separate process, as the real
  worker does: ``model.identify.identify`` (IGWO then TRF, on the reduced model) on a 60-min virtual-plant
  window, back to back. If the model or its cache is unavailable, a full-FE ``simulate`` loop is used and the
  output says so. The busy phase runs twice: with the identification process at the default priority and
  at ``--nice`` (default 10), to show what lowering the worker's priority buys the API.

Figures: medians over ``--runs`` runs of each run's p50/p99, and the busy/idle p99 ratio measured in the same
invocation. ``change_to_fresh_s`` (condition change detected with enough data -> fresh H) runs ``chtc demo``
(the whole service against simulated devices driven by the virtual plant, at ``--fresh-speedup``), waits for
the first condition change after start-up and for ``/chtc`` to turn fresh at the new condition, and adds up at
speed-up 1 the identification's wall time and the API pick-up (wall seconds from the stored result to the
fresh answer). ``condition_start_to_first_h_s`` adds the schedule delay in front (plant seconds from the
condition's start to the identification's start: the wait for ``identification.schedule_min[0]`` of data).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from benchmarks._api_load import _load, _server_buckets, histogram_quantile
from benchmarks._api_phases import bench_service, busy_phase, change_to_fresh, run_header, stop_process

TARGET_P99_MS = 10.0
TARGET_BUSY_RATIO = 2.0
TARGET_CHANGE_TO_FRESH_S = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument(
        "--served",
        action="store_true",
        help="the earlier bench: a served service fed a plant run, no devices (default: chtc demo, live)",
    )
    parser.add_argument("--rate", type=float, default=100.0, help="requests per second (default 100)")
    parser.add_argument("--clients", type=int, default=4, help="concurrent clients (default 4)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per run (default 10)")
    parser.add_argument("--runs", type=int, default=3, help="runs per phase; medians are quoted (default 3)")
    parser.add_argument(
        "--no-busy", action="store_true", help="skip the phase with an identification running"
    )
    parser.add_argument("--no-fresh", action="store_true", help="skip change_to_fresh_s (runs chtc demo)")
    parser.add_argument("--fresh-speedup", type=float, default=60.0, help="chtc demo speed-up (default 60)")
    parser.add_argument(
        "--fresh-segment-min", type=float, default=20.0, help="chtc demo plant minutes per speed (default 20)"
    )
    parser.add_argument("--no-field", action="store_true", help="skip the phase with field requests beside")
    parser.add_argument("--mesh-rate", type=float, default=2.0, help="field mesh requests/s (default 2)")
    parser.add_argument(
        "--points-rate", type=float, default=50.0, help="field points requests/s (default 50)"
    )
    parser.add_argument(
        "--field-period", type=float, default=10.0, help="s between field changes (a sample; default 10)"
    )
    from benchmarks.api_live import add_arguments as live_arguments

    live_arguments(parser)
    parser.add_argument(
        "--nice",
        type=int,
        default=10,
        help="also run the busy phase with the identification at this nice (0: skip)",
    )


# --- server subprocess ----------------------------------------------------------------------------------
def serve(port: int, field_period_s: float = 10.0) -> None:
    """Entry point of the server subprocess (uvicorn, one worker, the served real service); SIGTERM stops
    uvicorn gracefully, then the service and its temporary database."""
    import tempfile
    from pathlib import Path

    from service.settings import ApiSettings, Settings
    from simulator.served import exit_on_sigterm

    exit_on_sigterm()
    with (
        tempfile.TemporaryDirectory(prefix="chtc-bench-api-") as tmp,
        bench_service(Path(tmp), field_period_s=field_period_s) as (served, what),
    ):
        print(f"service: {what}", file=sys.stderr, flush=True)
        settings = Settings(api=ApiSettings(host="127.0.0.1", port=port))
        asyncio.run(serve_rest(settings, served.service, served.clock))


async def serve_rest(settings: Any, service: Any, clock: Any) -> None:
    """The REST outlet (``service.serve.outlet``, found by name: no import of ``api``) until it stops."""
    from service.serve.outlet import OutletContext, load_factory

    outlet: Any = load_factory("rest")(OutletContext(settings=settings, service=service, clock=clock))
    await outlet.start()
    try:
        await outlet.task
    finally:
        await outlet.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_server(field_period_s: float = 10.0) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    code = f"from benchmarks.api import serve; serve({port}, {field_period_s!r})"
    root = Path(__file__).resolve().parents[1]  # benchmarks/ is not installed: the child imports it from here
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=root
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(
                f"API server exited: {proc.stderr.read().decode()[-2000:] if proc.stderr else ''}"
            )
        try:
            if httpx.get(url + "/api/v1/chtc", timeout=1.0).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.05)
    proc.terminate()
    raise RuntimeError(f"API server did not answer on {url} within 120 s")


def _phase(url: str, args: argparse.Namespace) -> dict[str, Any]:
    """Alternating httpx / raw-socket runs (so both see the same machine load); medians per client kind."""
    out: dict[str, Any] = {"errors": 0}
    runs: dict[str, list[dict[str, Any]]] = {"httpx": [], "raw": []}
    for _ in range(args.runs):
        for kind, rs in runs.items():
            before = _server_buckets(url)
            r = asyncio.run(
                _load(
                    url + "/api/v1/chtc",
                    rate=args.rate,
                    duration_s=args.duration,
                    clients=args.clients,
                    kind=kind,
                )
            )
            after = _server_buckets(url)
            for q in (50, 99):
                v = histogram_quantile(q / 100, before, after)
                r[f"server_p{q}_ms"] = None if v is None else 1e3 * v
            rs.append(r)
            out["errors"] += r["errors"]
    for kind, rs in runs.items():
        out[kind] = {
            "p50_ms": statistics.median(r["p50_ms"] for r in rs),
            "p99_ms": statistics.median(r["p99_ms"] for r in rs),
            "late_ms_p99": statistics.median(r["late_ms_p99"] for r in rs),
            "server_p50_ms": statistics.median(r["server_p50_ms"] or math.nan for r in rs),
            "server_p99_ms": statistics.median(r["server_p99_ms"] or math.nan for r in rs),
            "runs": rs,
        }
    return out


# --- /chtc with field requests beside it -----------------------------------------------------------------
FIELD_POINTS = ";".join(f"{r:.3f},{z:.3f}" for r in (0.02, 0.05, 0.08, 0.1, 0.12) for z in (0.1, 0.3))


def _side_summary(rs: list[dict[str, Any]]) -> dict[str, Any]:
    statuses: dict[str, int] = {}
    for r in rs:
        for code, n in r["statuses"].items():
            statuses[str(code)] = statuses.get(str(code), 0) + n
    return {
        "p50_ms": statistics.median(r["p50_ms"] for r in rs),
        "p99_ms": statistics.median(r["p99_ms"] for r in rs),
        "late_ms_p99": statistics.median(r["late_ms_p99"] for r in rs),
        "statuses": statuses,
    }


def field_phase(url: str, args: argparse.Namespace) -> dict[str, Any]:
    """``/chtc`` (raw client) while ``--mesh-rate`` mesh (gzip) and ``--points-rate`` points (10 points)
    requests/s run beside it, open-loop, each on its own clients; medians over ``--runs``."""
    field = url + "/api/v1/temperature-field?at=now&format="
    runs: list[tuple[dict[str, Any], dict[str, Any], dict[str, Any]]] = []
    for _ in range(args.runs):

        async def together() -> Any:
            dur = args.duration
            return await asyncio.gather(
                _load(url + "/api/v1/chtc", rate=args.rate, duration_s=dur, clients=args.clients, kind="raw"),
                _load(
                    field + "mesh",
                    rate=args.mesh_rate,
                    duration_s=dur,
                    clients=2,
                    kind="raw",
                    headers="Accept-Encoding: gzip\r\n",
                ),
                _load(
                    field + "points&points=" + FIELD_POINTS,
                    rate=args.points_rate,
                    duration_s=dur,
                    clients=4,
                    kind="raw",
                ),
            )

        runs.append(asyncio.run(together()))
    chtc = [r[0] for r in runs]
    return {
        "raw": {
            "p50_ms": statistics.median(r["p50_ms"] for r in chtc),
            "p99_ms": statistics.median(r["p99_ms"] for r in chtc),
            "late_ms_p99": statistics.median(r["late_ms_p99"] for r in chtc),
            "server_p50_ms": math.nan,
            "server_p99_ms": math.nan,
            "runs": chtc,
        },
        "errors": sum(r["errors"] for r in chtc),
        "mesh": _side_summary([r[1] for r in runs]),
        "points": _side_summary([r[2] for r in runs]),
    }


# --- report -------------------------------------------------------------------------------------------
def run_bench(args: argparse.Namespace) -> dict[str, Any]:
    load_before = os.getloadavg()[0]
    proc, url = _start_server(args.field_period)
    try:
        idle = _phase(url, args)
        with_field = None if args.no_field else field_phase(url, args)
        busy = None if args.no_busy else busy_phase(url, args, nice=0, phase=_phase)
        niced = (
            None if args.no_busy or args.nice <= 0 else busy_phase(url, args, nice=args.nice, phase=_phase)
        )
    finally:
        stop_process(proc)
    fresh: dict[str, Any] = {"change_to_fresh_s": None, "change_to_fresh_reason": "skipped (--no-fresh)"}
    if not args.no_fresh:
        try:
            fresh = change_to_fresh(args)
        except Exception as err:  # report the failure in the figures instead of losing the latency ones
            fresh["change_to_fresh_reason"] = f"failed: {type(err).__name__}: {err}"
    hx, raw = idle["httpx"], idle["raw"]
    bhx, braw = (busy["httpx"], busy["raw"]) if busy else ({}, {})
    out: dict[str, Any] = {
        **run_header(args, load_before),
        "chtc_p50_ms": raw["p50_ms"],
        "chtc_p99_ms": raw["p99_ms"],
        "chtc_p50_ms_busy": braw.get("p50_ms"),
        "chtc_p99_ms_busy": braw.get("p99_ms"),
        "busy_over_idle_p99": braw["p99_ms"] / raw["p99_ms"] if busy else None,
        "chtc_p50_ms_field": with_field["raw"]["p50_ms"] if with_field else None,
        "chtc_p99_ms_field": with_field["raw"]["p99_ms"] if with_field else None,
        "field_over_idle_p99": with_field["raw"]["p99_ms"] / raw["p99_ms"] if with_field else None,
        "field_load": None
        if with_field is None
        else {
            "mesh_rps": args.mesh_rate,
            "points_rps": args.points_rate,
            "field_period_s": args.field_period,
            "mesh": with_field["mesh"],
            "points": with_field["points"],
        },
        "busy_nice": args.nice if niced else None,
        "chtc_p50_ms_busy_niced": niced["raw"]["p50_ms"] if niced else None,
        "chtc_p99_ms_busy_niced": niced["raw"]["p99_ms"] if niced else None,
        "busy_niced_over_idle_p99": niced["raw"]["p99_ms"] / raw["p99_ms"] if niced else None,
        "late_ms_p99": raw["late_ms_p99"],
        "server_p50_ms": raw["server_p50_ms"],
        "server_p99_ms": raw["server_p99_ms"],
        "server_p99_ms_busy": braw.get("server_p99_ms"),
        "server_p99_ms_busy_niced": niced["raw"]["server_p99_ms"] if niced else None,
        "httpx_p50_ms": hx["p50_ms"],
        "httpx_p99_ms": hx["p99_ms"],
        "httpx_p50_ms_busy": bhx.get("p50_ms"),
        "httpx_p99_ms_busy": bhx.get("p99_ms"),
        "httpx_late_ms_p99": hx["late_ms_p99"],
        "busy_load": busy["load"] if busy else None,
        "identifications_during_busy": busy["identifications_during_load"] if busy else None,
        "identification_wall_s_median": busy["identification_wall_s_median"] if busy else None,
        "errors": idle["errors"]
        + (busy["errors"] if busy else 0)
        + (with_field["errors"] if with_field else 0),
        **fresh,
        "target_p99_ms": TARGET_P99_MS,
        "target_busy_ratio": TARGET_BUSY_RATIO,
        "target_change_to_fresh_s": TARGET_CHANGE_TO_FRESH_S,
        "idle": idle,
        "busy": busy,
        "busy_niced": niced,
        "with_field": with_field,
    }
    out["meets_idle_target"] = out["chtc_p99_ms"] <= TARGET_P99_MS
    # the service runs its identification worker at nice WORKER_NICE (service.identify.worker): the niced
    # phase is the
    # service's configuration when it ran; the default-priority phase is shown beside it
    busy_ratio = out["busy_niced_over_idle_p99"] if niced else out["busy_over_idle_p99"]
    out["busy_target_ratio"] = busy_ratio
    out["meets_busy_target"] = None if busy_ratio is None else busy_ratio <= TARGET_BUSY_RATIO
    out["meets_field_target"] = (
        None if with_field is None else out["field_over_idle_p99"] <= TARGET_BUSY_RATIO
    )
    fresh_s = out.get("change_to_fresh_s")
    out["meets_change_to_fresh_target"] = None if fresh_s is None else fresh_s <= TARGET_CHANGE_TO_FRESH_S
    return out


def _rows(r: dict[str, Any]) -> list[str]:
    def f(v: Any) -> str:
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.2f}"

    out = []
    for kind in ("raw", "httpx"):
        for label, key in (
            ("idle", "idle"),
            ("busy", "busy"),
            ("busy+nice", "busy_niced"),
            ("field", "with_field"),
        ):
            ph = (r.get(key) or {}).get(kind)
            if ph is not None:
                cells = [ph["p50_ms"], ph["p99_ms"], ph["server_p50_ms"], ph["server_p99_ms"]]
                out.append(
                    f"{kind:<8}{label:<10}"
                    + "".join(f"{f(c):>9}" if k < 2 else f"{f(c):>12}" for k, c in enumerate(cells))
                )
    return out


def _met(v: bool | None) -> str:
    return "-" if v is None else "met" if v else "MISSED"


def _field_line(fl: dict[str, Any] | None) -> str:
    if fl is None:
        return "skipped (--no-field)"
    parts = []
    for kind, rps in (("mesh", fl["mesh_rps"]), ("points", fl["points_rps"])):
        d = fl[kind]
        parts.append(
            f"{kind} {rps:g}/s p50 {d['p50_ms']:.1f} / p99 {d['p99_ms']:.1f} ms, statuses {d['statuses']}"
        )
    return "; ".join(parts) + f" (field changes every {fl['field_period_s']:g} s)"


def _table(r: dict[str, Any]) -> str:
    def f(v: Any) -> str:
        return "-" if v is None else f"{v:.2f}" if isinstance(v, float) else str(v)

    lines = [
        f"GET /api/v1/chtc at {r['rate_rps']:.0f} req/s, {r['clients']} clients, {r['runs']} x "
        f"{r['duration_s']} s per phase and client, {r['cpus']} CPUs, "
        f"load avg {f(r['loadavg_1min_at_start'])} "
        "at start (medians over runs)",
        f"{'client':<8}{'phase':<8}{'p50 ms':>9}{'p99 ms':>9}{'server p50':>12}{'server p99':>12}",
        *_rows(r),
        f"(busy+nice: identification process at nice {r['busy_nice']}; server = the API's own latency "
        "histogram for the same requests, interpolated within buckets)",
        f"sends behind schedule, p99: raw {f(r['late_ms_p99'])} ms, httpx {f(r['httpx_late_ms_p99'])} ms "
        "(large = the client itself is saturated)",
        f"targets (raw /chtc p99): idle <= {r['target_p99_ms']:.0f} ms: {_met(r['meets_idle_target'])}; "
        f"during identification (worker at nice {r['busy_nice']}) <= {r['target_busy_ratio']:.0f}x idle "
        f"({f(r['busy_target_ratio'])}x; default priority {f(r['busy_over_idle_p99'])}x): "
        f"{_met(r['meets_busy_target'])}; with field requests beside <= {r['target_busy_ratio']:.0f}x idle "
        f"({f(r.get('field_over_idle_p99'))}x): {_met(r.get('meets_field_target'))}",
        f"field load beside /chtc: {_field_line(r.get('field_load'))}",
        f"/chtc on the whole running service (chtc demo): {r.get('full_service_chtc_ms')}",
        f"busy load: {r['busy_load']} ({r['identifications_during_busy']} runs, median "
        f"{f(r['identification_wall_s_median'])} s each)",
        f"errors: {r['errors']}",
        f"change_to_fresh_s (enough data -> fresh H): {f(r['change_to_fresh_s'])}; "
        f"condition_start_to_first_h_s: {f(r.get('condition_start_to_first_h_s'))} = "
        + " + ".join(f"{k} {f(v)}" for k, v in r.get("change_to_fresh_parts", {}).items())
        + f" ({r['change_to_fresh_reason']})",
    ]
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    if not args.served:  # the service users run (benchmarks.api_live)
        from benchmarks.api_live import live_bench, table

        live = live_bench(args)
        print(json.dumps(live, indent=2) if args.json else table(live))
        return 0
    result = run_bench(args)
    print(json.dumps(result, indent=2) if args.json else _table(result))
    return 0
