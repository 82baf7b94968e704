"""Helpers of ``python -m benchmarks api`` (see :mod:`benchmarks.api`): the served service, the busy load (an
identification loop in a separate process), the change-to-fresh measurement through ``chtc demo``, and process
clean-up."""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

Phase = Callable[[str, argparse.Namespace], dict[str, Any]]


def run_header(args: argparse.Namespace, load_before: float) -> dict[str, Any]:
    """What every ``python -m benchmarks api`` report starts with: the load offered, the runs, the machine."""
    return {
        "rate_rps": args.rate,
        "clients": args.clients,
        "duration_s": args.duration,
        "runs": args.runs,
        "cpus": os.cpu_count(),
        "loadavg_1min_at_start": load_before,
    }


def stop_process(proc: subprocess.Popen[Any] | mp.process.BaseProcess) -> None:
    proc.terminate()
    if isinstance(proc, subprocess.Popen):
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    else:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
            proc.join()


# --- the server's service: the real one, fed a virtual-plant run ---------------------------------------
@contextmanager
def bench_service(tmp: Path, *, field_period_s: float = 10.0) -> Iterator[tuple[Any, str]]:
    """The served service the benchmark's API serves (``simulator.served``: the real core and shell on
    SQLite in ``tmp``, fed the demo plan's first 22 min: two identifications, fresh) and a line saying what
    it is. The next samples follow every ``field_period_s`` wall seconds (5 min of them at 4000 rpm, before
    the next scheduled identification), so the live field changes as with a running acquisition."""
    from simulator.served import DEMO_FED, served_service

    with served_service(database_url=f"sqlite:///{tmp / 'chtc.db'}", feed_samples=DEMO_FED) as served:
        stop = served.feed_every(field_period_s)
        f = served.service.field("now")
        try:
            yield served, f"the real service (demo plan) on its FE mesh: {len(f.nodes_rz)} nodes"
        finally:
            stop.set()


# --- busy: an identification loop in another process -----------------------------------------------------
def _identification_setup() -> tuple[Any, Any, str]:
    from model.identify import Window, identify
    from model.inputs import inputs_from_operation
    from model.plant import Segment, VirtualPlant
    from service.modelload import ModelRef, load_model
    from service.settings import Settings

    model = load_model(ModelRef.from_settings(Settings()))  # CHTC_MODEL__ROM_CACHE_DIR, as before
    run = VirtualPlant(model.spec, seed=1).run([Segment(3600.0, 4000.0, 14.0, 21.8)], dt_s=10.0)
    inputs = inputs_from_operation(
        model.spec,
        dt_s=10.0,
        speed_rpm=run.speed_rpm[:-1],
        torque_nm=run.torque_nm[:-1],
        ambient_c=run.ambient_c[:-1],
    )
    window = Window(inputs, run.temps_c, np.ones(32, dtype=bool), float(run.ambient_c[0]))
    seed = iter(range(10**9))

    def once() -> None:
        identify(model.rom, window, rng=next(seed), method="hybrid")

    return once, model, "model.identify.identify(method='hybrid') on the reduced model, 60-min plant window"


def _fe_setup() -> tuple[Any, Any, str]:
    from model.fem import build_fe_model, simulate
    from model.geometry import load_spindle
    from model.inputs import inputs_from_operation

    spec = load_spindle()
    fe = build_fe_model(spec)
    inputs = inputs_from_operation(
        spec, dt_s=10.0, speed_rpm=np.full(360, 4000.0), torque_nm=14.0, ambient_c=21.8
    )
    h = np.array([80.0, 46.0, 62.0, 45.0, 46.0, 68.0, 11.0])

    def once() -> None:
        simulate(fe, h, inputs, 21.8)

    return once, fe, "full-FE model.fem.simulate (360 steps) loop (model.identify or its cache unavailable)"


def _busy_main(ready: Any, stop: Any, results: Any, nice: int) -> None:
    if nice:
        os.nice(nice)
    try:
        once, _, what = _identification_setup()
        once()
    except Exception as err:  # any failure of the real path: fall back, and say why
        once, _, what = _fe_setup()
        what += f" [{type(err).__name__}: {str(err)[:120]}]"
    results.put(("what", what))
    ready.set()
    walls = []
    while not stop.is_set():
        t = time.perf_counter()
        once()
        walls.append(time.perf_counter() - t)
    results.put(("walls", walls))


def _start_busy(nice: int) -> tuple[mp.process.BaseProcess, Any, Any, str]:
    ctx = mp.get_context("spawn")
    ready, stop, results = ctx.Event(), ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_busy_main, args=(ready, stop, results, nice), daemon=True)
    proc.start()
    if not ready.wait(timeout=600):
        stop_process(proc)
        raise RuntimeError("the identification process did not get ready within 600 s")
    return proc, stop, results, results.get(timeout=10)[1]


def busy_phase(url: str, args: argparse.Namespace, *, nice: int, phase: Phase) -> dict[str, Any]:
    proc, stop, results, what = _start_busy(nice)
    try:
        out = phase(url, args)
    finally:
        stop.set()
        try:
            walls = results.get(timeout=120)[1]
        except Exception:
            walls = []
        stop_process(proc)
    out["load"] = what
    out["identifications_during_load"] = len(walls)
    out["identification_wall_s_median"] = statistics.median(walls) if walls else None
    return out


# --- condition change -> fresh H, through the whole running service (chtc demo) ------------------------
def _start_demo(args: argparse.Namespace) -> tuple[subprocess.Popen[str], str]:
    return start_demo(
        [
            "--duration",
            "900",
            "--speedup",
            str(args.fresh_speedup),
            "--segment-min",
            str(args.fresh_segment_min),
        ]
    )


def start_demo(options: list[str]) -> tuple[subprocess.Popen[str], str]:
    """``chtc demo --port 0 --quiet`` with ``options`` in a child process; returns it and its dashboard URL
    (``RuntimeError`` when it exits or prints none within 600 s)."""
    cmd = [sys.executable, "-m", "service.cli", "demo", "--port", "0", "--quiet", *options]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    found: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if not found and (m := re.search(r"dashboard: (http://[^\s#]+?)/?[\s#]", line)):
                found.append(m.group(1))

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + 600.0
    while not found and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    if not found:
        stop_process(proc)
        raise RuntimeError("chtc demo did not print its URL (exited or took > 600 s)")
    return proc, found[0]


def _poll_change_then_fresh(
    c: httpx.Client, timeout_s: float, lat: list[float]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Wait for a new condition id after the first one seen, then for /chtc fresh at that condition.
    ``lat`` collects the /chtc round trips (s) on the way."""
    first: int | None = None
    change: dict[str, Any] | None = None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = c.get("/api/v1/condition")
        if r.status_code == 200:
            cond = r.json()["current"]
            if first is None:
                first = cond["id"]
            elif change is None and cond["id"] != first:
                change = cond
        if change is not None:
            t = time.perf_counter()
            h = c.get("/api/v1/chtc")
            lat.append(time.perf_counter() - t)
            body = h.json() if h.status_code == 200 else {}
            if body.get("status") == "fresh" and body["condition"]["id"] == change["id"]:
                return change, body
        time.sleep(0.05)
    raise RuntimeError(f"no condition change followed by fresh H within {timeout_s:.0f} s (first={first})")


def change_to_fresh(args: argparse.Namespace) -> dict[str, Any]:
    """Condition change -> fresh H through the whole service (``chtc demo``: simulated devices, real drivers,
    detector, scheduler, worker process, database, API), split into its parts and re-added at speed-up 1."""
    proc, url = _start_demo(args)
    lat: list[float] = []
    try:
        with httpx.Client(base_url=url, timeout=10.0) as c:
            cond, fresh = _poll_change_then_fresh(
                c, lat=lat, timeout_s=60.0 * 3 * args.fresh_segment_min / args.fresh_speedup + 120
            )
            rec = c.get(f"/api/v1/identifications/{fresh['identification_id']}").json()
    finally:
        stop_process(proc)

    def ts(key: str, d: dict[str, Any]) -> datetime:
        return datetime.fromisoformat(d[key])

    ms = np.array(lat or [float("nan")]) * 1e3
    schedule_plant_s = (ts("started_at", rec) - ts("since", cond)).total_seconds()
    pickup_wall_s = (ts("served_at", fresh) - ts("finished_at", rec)).total_seconds() / args.fresh_speedup
    return {
        # the definition: from the moment enough data of the new condition exist (the schedule fires)
        # to the new H being served
        "change_to_fresh_s": rec["wall_s"] + pickup_wall_s,
        # and from the detector's condition start, including the wait for a first window's worth of data
        "condition_start_to_first_h_s": schedule_plant_s + rec["wall_s"] + pickup_wall_s,
        "change_to_fresh_parts": {
            "schedule_delay_s": schedule_plant_s,
            "identification_wall_s": rec["wall_s"],
            "api_pickup_s": pickup_wall_s,
        },
        "change_to_fresh_measured_plant_s": (ts("served_at", fresh) - ts("since", cond)).total_seconds(),
        "change_to_fresh_speedup": args.fresh_speedup,
        "full_service_chtc_ms": {
            "n": len(lat),
            "p50": float(np.percentile(ms, 50)),
            "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max()),
            "note": "sequential httpx GETs, ~20/s, on chtc demo's API while it ran (incl. httpx)",
        },
        "change_to_fresh_reason": f"chtc demo at x{args.fresh_speedup:g}: condition {cond['id']} "
        f"({cond['speed_rpm']:.0f} rpm) -> identification {rec['id']} ({rec['method']}); schedule delay "
        "(plant s, set by identification.schedule_min[0]) + identification wall s + API pick-up; "
        "change_to_fresh_s leaves out the schedule delay (enough data -> fresh H)",
    }
