"""``python -m benchmarks api`` on the service users run (issue 30): ``chtc demo`` (simulated devices, real
drivers, the live filter, the growth, the speed map in combined mode, the worker process) at real rate and at
×60, loaded with ``GET /api/v1/chtc`` open loop, quiet and beside a CPU hog.

Per speed-up (``--speedups``, default ``1,60``) one ``chtc demo`` subprocess runs; after ``--warmup`` wall
seconds, each of ``--runs`` runs loads it for ``--duration`` s quiet, then for ``--duration`` s beside a hog
(``os.cpu_count()`` busy processes started by the bench, killed at the end of the phase). The bench polls
``/healthz`` every 0.1 s meanwhile, so each request is classed by whether an identification was running when
it was sent (``p99_ratio_identifying``: their p99 over the others'). The event loop's lag comes from the
service's own histogram ``chtc_event_loop_lag_seconds`` between scrapes before and after each phase: its
maximum is the upper bound of the highest bucket observed (buckets 1, 2, 5, 10, 20, 50, 100, ... ms).
At the end: the demo's device timeouts and identifications by outcome, and (``--cpu-window`` s, at real
rate, no requests) the CPU of the demo's processes per core (``cpu_percent_of_core``) and of the service
alone (``cpu_service_percent_of_core``: without the child process ``chtc-rig`` that holds the simulated
devices and the virtual plant, which a ``chtc run`` does not have). Figures are medians over the runs.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing as mp
import os
import statistics
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

from benchmarks._api_phases import run_header, stop_process
from benchmarks._api_phases import start_demo as _start

TARGETS = {
    "quiet_p99_ms": 10.0,
    "quiet_p99_ratio_identifying": 2.0,
    "quiet_loop_lag_max_ms": 50.0,
    "hog_p99_ms": 100.0,
    "hog_max_ms": 500.0,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speedups", default="1,60", help="demo speed-ups to measure (default 1,60)")
    parser.add_argument("--warmup", type=float, default=20.0, help="wall s before the first run (default 20)")
    parser.add_argument("--cpu-window", type=float, default=30.0, help="s of CPU at real rate (0: skip)")
    parser.add_argument("--short", action="store_true", help="1 run of 3 s, ×60 only, 5 s warm-up (tests)")


# --- the demo -------------------------------------------------------------------------------------------
def start_demo(speedup: float, seed: int = 0) -> tuple[subprocess.Popen[str], str]:
    """``chtc demo`` at ``speedup`` for up to 10 h (``_api_phases.start_demo``)."""
    return _start(["--speedup", str(speedup), "--seed", str(seed), "--duration", "36000"])


def process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of ``pid`` and its living children (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for p in [pid, *_children(pid)]:
        with contextlib.suppress(OSError):
            fields = _read(f"/proc/{p}/stat").rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def rig_pids(pid: int) -> list[int]:
    """The demo's rig process (``simulator.rigproc``, named ``chtc-rig``) among ``pid``'s children."""
    from simulator.rigproc import PROCESS_NAME

    out = []
    for c in _children(pid):
        with contextlib.suppress(OSError):
            if _read(f"/proc/{c}/comm").strip() == PROCESS_NAME:
                out.append(c)
    return out


def _children(pid: int) -> list[int]:
    out: list[int] = []
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError):
                out += [int(c) for c in _read(f"/proc/{pid}/task/{tid}/children").split()]
    return out


def _read(path: str) -> str:
    with open(path) as f:
        return f.read()


# --- the hog ---------------------------------------------------------------------------------------------
def _spin() -> None:
    while True:
        pass


@contextlib.contextmanager
def cpu_hog(n: int | None = None) -> Iterator[list[mp.process.BaseProcess]]:
    """``n`` (default: one per core) busy processes for the block; killed at its end, whatever happens."""
    ctx = mp.get_context("spawn")
    procs: list[mp.process.BaseProcess] = [
        ctx.Process(target=_spin, daemon=True) for _ in range(n or os.cpu_count() or 1)
    ]
    try:
        for p in procs:
            p.start()
        yield procs
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
            p.join(10)


# --- one phase -------------------------------------------------------------------------------------------
def _metric_samples(url: str) -> list[Any]:
    text = httpx.get(url + "/api/v1/metrics", timeout=10.0).text
    return [s for fam in text_string_to_metric_families(text) for s in fam.samples]


def _lag_buckets(samples: list[Any]) -> dict[float, float]:
    return {float(s.labels["le"]): s.value for s in samples if s.name == "chtc_event_loop_lag_seconds_bucket"}


def lag_max_bound_s(before: dict[float, float], after: dict[float, float]) -> float:
    """The upper bound [s] of the highest bucket that got observations between two scrapes (0: none)."""
    top = 0.0
    prev = 0.0
    for le in sorted(after):
        n = after[le] - before.get(le, 0.0)
        if n > prev:
            top = le
        prev = n
    return top


def classify(
    sent: list[float], lat: list[float], marks: list[tuple[float, bool]]
) -> tuple[list[float], list[float]]:
    """Latencies of requests sent while an identification ran, and of the others (``marks``: (t, running)
    polls in time order; a request takes the state of the last poll before it)."""
    times = np.array([t for t, _ in marks]) if marks else np.array([])
    busy: list[float] = []
    idle: list[float] = []
    for t, v in zip(sent, lat, strict=True):
        k = int(np.searchsorted(times, t, side="right")) - 1
        (busy if k >= 0 and marks[k][1] else idle).append(v)
    return busy, idle


async def _poll_running(url: str, stop: asyncio.Event, marks: list[tuple[float, bool]]) -> None:
    async with httpx.AsyncClient(timeout=5.0) as c:
        while not stop.is_set():
            with contextlib.suppress(httpx.HTTPError):
                r = (await c.get(url + "/healthz")).json()
                worker: dict[str, Any] = next((d for d in r["devices"] if d["name"] == "worker"), {})
                marks.append((time.perf_counter(), str(worker.get("message", "")).startswith("running")))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 0.1)


async def _loaded(url: str, rate: float, duration_s: float, clients: int) -> dict[str, Any]:
    from benchmarks._api_load import _load

    marks: list[tuple[float, bool]] = []
    records: list[tuple[float, float]] = []
    stop = asyncio.Event()
    poller = asyncio.ensure_future(_poll_running(url, stop, marks))
    try:
        r = await _load(
            url + "/api/v1/chtc",
            rate=rate,
            duration_s=duration_s,
            clients=clients,
            kind="raw",
            records=records,
        )
    finally:
        stop.set()
        await poller
    busy, idle = classify([t for t, _ in records], [v for _, v in records], marks)
    r["identifying_n"], r["not_identifying_n"] = len(busy), len(idle)
    r["p99_ms_identifying"] = float(np.percentile(busy, 99) * 1e3) if len(busy) >= 20 else None
    r["p99_ms_not_identifying"] = float(np.percentile(idle, 99) * 1e3) if len(idle) >= 20 else None
    return r


def phase(url: str, args: argparse.Namespace, *, hog: bool) -> dict[str, Any]:
    """One load phase; the service's own histograms (event-loop lag, /chtc request duration as uvicorn's
    app saw it) between scrapes before and after it."""
    from benchmarks._api_load import _server_buckets, histogram_quantile

    before, server0 = _lag_buckets(_metric_samples(url)), _server_buckets(url)
    with cpu_hog() if hog else contextlib.nullcontext():
        r = asyncio.run(_loaded(url, args.rate, args.duration, args.clients))
    after, server1 = _lag_buckets(_metric_samples(url)), _server_buckets(url)
    r["loop_lag_max_ms"] = 1e3 * lag_max_bound_s(before, after)
    for name, q, b0, b1 in (
        ("loop_lag_p99_ms", 0.99, before, after),
        ("server_p50_ms", 0.5, server0, server1),
        ("server_p99_ms", 0.99, server0, server1),
    ):
        v = histogram_quantile(q, b0, b1)
        r[name] = None if v is None else 1e3 * v
    return r


def cpu_split(pid: int, window_s: float) -> dict[str, float | None]:
    """CPU [% of a core] over ``window_s`` of the demo's processes (``cpu_percent_of_core``), and of the
    service alone (``cpu_service_percent_of_core``: the demo's own process and its worker, without the rig
    process that holds the simulated devices and the plant, as ``chtc run`` is)."""
    rigs = rig_pids(pid)
    t0 = time.monotonic()
    c0, r0 = process_cpu_s(pid), sum(process_cpu_s(r) for r in rigs)
    time.sleep(window_s)
    dt = time.monotonic() - t0
    whole = 100.0 * (process_cpu_s(pid) - c0) / dt
    rig = 100.0 * (sum(process_cpu_s(r) for r in rigs) - r0) / dt
    return {"cpu_percent_of_core": whole, "cpu_service_percent_of_core": whole - rig if rigs else None}


def _counters(url: str) -> dict[str, Any]:
    s = _metric_samples(url)
    ident = {x.labels["outcome"]: x.value for x in s if x.name == "chtc_identifications_total"}
    polls = {x.labels["outcome"]: x.value for x in s if x.name == "chtc_modbus_polls_total"}
    terms = next((x.value for x in s if x.name == "chtc_growth_terms_computed_total"), None)
    terms_cpu = next((x.value for x in s if x.name == "chtc_growth_terms_cpu_seconds_total"), None)
    dropped = next((x.value for x in s if x.name == "chtc_core_dropped_samples_total"), None)
    return {
        "identifications": ident,
        "device_timeouts": polls.get("device_timeout", 0.0),
        "growth_terms_computed": terms,
        "growth_terms_cpu_s": terms_cpu,
        "core_dropped_samples": dropped,
    }


def _median(rs: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rs if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def one_speedup(speedup: float, args: argparse.Namespace) -> dict[str, Any]:
    proc, url = start_demo(speedup)
    try:
        time.sleep(args.warmup)
        started = time.monotonic()
        quiet, hog = [], []
        for _ in range(args.runs):
            quiet.append(phase(url, args, hog=False))
            hog.append(phase(url, args, hog=True))
        wall = time.monotonic() - started
        cpu: dict[str, float | None] = {"cpu_percent_of_core": None, "cpu_service_percent_of_core": None}
        if speedup == 1.0 and args.cpu_window > 0:
            cpu = cpu_split(proc.pid, args.cpu_window)
        counters = _counters(url)
    finally:
        stop_process(proc)
    out: dict[str, Any] = {"speedup": speedup, "measured_wall_s": wall, **cpu}
    for name, rs in (("quiet", quiet), ("hog", hog)):
        out[name] = {
            k: _median(rs, k)
            for k in (
                "p50_ms",
                "p99_ms",
                "max_ms",
                "p99_ms_identifying",
                "p99_ms_not_identifying",
                "loop_lag_max_ms",
                "loop_lag_p99_ms",
                "server_p50_ms",
                "server_p99_ms",
                "late_ms_p99",
            )
        }
        out[name]["identifying_requests"] = sum(r["identifying_n"] for r in rs)
        out[name]["errors"] = sum(r["errors"] for r in rs)
        out[name]["runs"] = rs
    out.update(counters)
    return out


def _worst(per: list[dict[str, Any]], part: str, key: str) -> float | None:
    vals = [p[part][key] for p in per if p[part].get(key) is not None]
    return max(vals) if vals else None


def live_bench(args: argparse.Namespace) -> dict[str, Any]:
    if args.short:
        args.runs, args.duration, args.warmup, args.speedups, args.cpu_window = 1, 3.0, 5.0, "60", 0.0
    speedups = [float(x) for x in args.speedups.split(",") if x.strip()]
    load_before = os.getloadavg()[0]
    per = [one_speedup(s, args) for s in speedups]
    busy = [p["quiet"]["p99_ms_identifying"] for p in per if p["quiet"]["p99_ms_identifying"] is not None]
    calm = [p["quiet"]["p99_ms_not_identifying"] for p in per if p["quiet"]["p99_ms_identifying"] is not None]
    ratio = max(b / c for b, c in zip(busy, calm, strict=True) if c) if busy and all(calm) else None
    out: dict[str, Any] = {
        **run_header(args, load_before),
        "quiet": {
            "p99_ms": _worst(per, "quiet", "p99_ms"),
            "max_ms": _worst(per, "quiet", "max_ms"),
            "p99_ratio_identifying": ratio,
            "loop_lag_max_ms": _worst(per, "quiet", "loop_lag_max_ms"),
        },
        "hog": {
            "p99_ms": _worst(per, "hog", "p99_ms"),
            "max_ms": _worst(per, "hog", "max_ms"),
            "loop_lag_max_ms": _worst(per, "hog", "loop_lag_max_ms"),
        },
        "per_speedup": {f"x{p['speedup']:g}": p for p in per},
        "targets": TARGETS,
    }
    q, h = out["quiet"], out["hog"]
    met = {
        "quiet_p99_ms": q["p99_ms"],
        "quiet_p99_ratio_identifying": q["p99_ratio_identifying"],
        "quiet_loop_lag_max_ms": q["loop_lag_max_ms"],
        "hog_p99_ms": h["p99_ms"],
        "hog_max_ms": h["max_ms"],
    }
    out["meets"] = {k: None if v is None else v <= TARGETS[k] for k, v in met.items()}
    return out


def table(r: dict[str, Any]) -> str:
    def f(v: Any) -> str:
        return "-" if v is None else f"{v:.2f}" if isinstance(v, float) else str(v)

    lines = [
        f"GET /api/v1/chtc on chtc demo, {r['rate_rps']:g} req/s open loop, {r['clients']} clients, "
        f"{r['runs']} x {r['duration_s']:g} s per phase, {r['cpus']} CPUs, load avg "
        f"{r['loadavg_1min_at_start']:.2f} at start (medians over runs)",
        f"{'speed-up':<9}{'phase':<7}{'p50':>8}{'p99':>8}{'max':>9}{'p99 ident':>11}{'p99 other':>11}"
        f"{'loop lag max':>14}",
    ]
    for name, p in r["per_speedup"].items():
        for part in ("quiet", "hog"):
            d = p[part]
            lines.append(
                f"{name:<9}{part:<7}{f(d['p50_ms']):>8}{f(d['p99_ms']):>8}{f(d['max_ms']):>9}"
                f"{f(d['p99_ms_identifying']):>11}{f(d['p99_ms_not_identifying']):>11}"
                f"{'<= ' + f(d['loop_lag_max_ms']):>14}"
            )
        lines.append(
            f"{'':9}identifications {p['identifications']}, device timeouts {p['device_timeouts']:g}, "
            f"growth terms {f(p['growth_terms_computed'])} ({f(p['growth_terms_cpu_s'])} CPU s), "
            f"CPU {f(p['cpu_percent_of_core'])} % of a core (service {f(p['cpu_service_percent_of_core'])})"
        )
    q = r["quiet"]
    lines.append(
        "bars: " + ", ".join(f"{k} <= {v:g}: {_met(r['meets'][k])}" for k, v in r["targets"].items())
    )
    lines.append(
        f"quiet p99 {f(q['p99_ms'])} ms, ratio identifying {f(q['p99_ratio_identifying'])}, "
        f"loop lag max <= {f(q['loop_lag_max_ms'])} ms; hog p99 {f(r['hog']['p99_ms'])} ms, "
        f"max {f(r['hog']['max_ms'])} ms"
    )
    return "\n".join(lines)


def _met(v: bool | None) -> str:
    return "-" if v is None else "met" if v else "MISSED"
