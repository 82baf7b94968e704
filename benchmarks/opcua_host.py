"""``python -m benchmarks opcua --spindles N`` (N > 1): the hosted OPC UA server (one server, one object per
spindle; issue 43, "Bars") under 10 PLC-like clients, quiet and beside a CPU hog, and what it costs REST.

Set-up, as ``python -m benchmarks fleet`` starts a host (``benchmarks.fleet_host``): the devices of N
spindles at their real rates in one child process (nice 10, the last core), one PostgreSQL schema, and the
product, ``chtc run --config host.toml --migrate`` with N ``[[spindles]]`` (pinned to the other cores). The
product is started ``--runs`` times with the outlets off and ``--runs`` times with ``[opcua] enabled``,
alternating (off, on, off, on, ...); the devices and the schema stay. In every phase, after each spindle's
``/compensation`` answers and ``--settle`` s more:

- **REST**: GET ``/api/v1/spindles/{id}/compensation`` at ``--rate`` requests/s over ``--rest-clients``
  keep-alive connections, request i to spindle i mod N, for ``--duration`` s (in this process);
- **on** phases: the readers (``benchmarks.opcua_clients``, a subprocess): ``--clients`` asyncua clients ×
  ``--read-rate`` reads/s of 10 nodes, spread over the spindles, during the same REST load;
- the first **on** phase first browses every spindle's object and compares its values and StatusCodes with
  its REST answer at the same ``at`` (``equal_to_rest``);
- the last **on** phase then repeats readers and REST beside ``os.cpu_count()`` busy-loop processes (the
  hog phase: ``read_p99_ms_hog``).

``rest_p99_ratio_outlets_on`` = median over the on phases of REST p99 / the same over the off phases.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.fleet_host import (
    Outlets,
    _get,
    _wait,
    devices,
    free_port,
    fresh_schema,
    host_toml,
    product,
    say,
)
from benchmarks.opcua_figures import median_or_none, percentile, rest_ratio

__all__ = ["BARS", "run_host_bench"]

ROOT = Path(__file__).resolve().parents[1]
BARS = {"read_p99_ms": 10.0, "rest_p99_ratio_outlets_on": 1.5, "read_p99_ms_hog": 100.0}


def run_host_bench(n: int, args: argparse.Namespace) -> dict[str, Any]:
    """The phases for N hosted spindles; the figures (see the module docstring)."""
    utc = datetime.now(UTC).isoformat(timespec="seconds")
    load_before = os.getloadavg()[0]
    ids = [f"bench-{i + 1:03d}" for i in range(n)]
    offs: list[dict[str, Any]] = []
    ons: list[dict[str, Any]] = []
    hours = (args.runs * 2 * (args.duration + 120.0) + 2 * args.duration) / 3600.0 + 0.5
    with (
        tempfile.TemporaryDirectory(prefix="chtc-bench-opcua-") as tmp,
        devices(n, plants=args.plants, hours=hours) as (modbus, can),
        fresh_schema(args.pg_url) as (_schema, url, _admin),
    ):
        for run in range(args.runs):
            for on in (False, True):
                outlets = Outlets(opcua_port=free_port() if on else 0, max_connections=args.clients + 2)
                config = Path(tmp) / f"host-{n}-{run}-{'on' if on else 'off'}.toml"
                api_port = free_port()
                config.write_text(host_toml(url, api_port, modbus, can, outlets), encoding="utf-8")
                with product(config, config.with_suffix(".log"), api_port):
                    phase = _Phase(n, ids, api_port, outlets.opcua_port, args)
                    phase.wait_answers()
                    time.sleep(args.settle)  # the start's own work (first live fields, jobs) passes
                    first_on, last_on = on and not ons, on and run == args.runs - 1
                    (ons if on else offs).append(phase.run(check=first_on, hog=last_on))
                state = "on" if on else "off"
                say(f"N={n}: run {run + 1}/{args.runs} {state}: {_brief((ons if on else offs)[-1])}")
    return _figures(n, ids, offs, ons, args, utc=utc, load_before=load_before)


class _Phase:
    """One product start: REST load, and with OPC UA on its readers, the check, the hog."""

    def __init__(self, n: int, ids: list[str], api_port: int, opcua_port: int, args: argparse.Namespace):
        self.n, self.ids, self.args = n, ids, args
        self.rest = f"http://127.0.0.1:{api_port}"
        self.endpoint = f"opc.tcp://127.0.0.1:{opcua_port}/chtc" if opcua_port else ""

    def wait_answers(self) -> None:
        """Every spindle's ``/compensation`` answers 200 (its first live field), within 300 s."""

        def all_answer() -> bool:
            return all(_get(f"{self.rest}/api/v1/spindles/{sid}/compensation")[0] == 200 for sid in self.ids)

        _wait(all_answer, 300.0, "every spindle's /compensation")

    def run(self, *, check: bool, hog: bool) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if check:
            from benchmarks.opcua_clients import equal_to_rest

            out["equal_to_rest"] = asyncio.run(equal_to_rest(self.endpoint, self.rest, self.ids))
            say(f"N={self.n}: equal to REST: {out['equal_to_rest']['equal']}")
        out["quiet"] = self._load()
        if hog:
            with _hogs(os.cpu_count() or 1):
                out["hog"] = self._load()
        return out

    def _load(self) -> dict[str, Any]:
        """REST load, with the readers during it when OPC UA is on."""
        if not self.endpoint:
            return {"rest": _rest_load(self.rest, self.ids, self.args)}
        with _Readers(self.endpoint, self.ids, self.args) as readers:
            rest = _rest_load(self.rest, self.ids, self.args)
        return {"rest": rest, "opcua": readers.result}


class _Readers:
    """The readers' subprocess: entered once its clients are connected; its result after exit."""

    def __init__(self, endpoint: str, ids: list[str], args: argparse.Namespace) -> None:
        cfg = {
            "endpoint": endpoint,
            "spindles": ids,
            "clients": args.clients,
            "read_rate": args.read_rate,
            "duration_s": args.duration,
        }
        code = f"from benchmarks.opcua_clients import readers; readers({json.dumps(cfg)!r})"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
        )
        self.result: dict[str, Any] = {}
        self.timeout_s = 120.0 + 2 * args.duration

    def __enter__(self) -> _Readers:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith('{"connected"'):
            self._fail(f"did not connect (said {line.strip()!r})")
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            stdout, stderr = self.proc.communicate(timeout=self.timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            stdout, stderr = self.proc.communicate()
        lines = [x for x in stdout.splitlines() if x.startswith("{")]
        if self.proc.returncode != 0 or not lines:
            if exc[0] is None:
                raise RuntimeError(f"the OPC UA readers failed: {stderr[-2000:]}")
            return
        r = json.loads(lines[-1])
        self.result = {
            "latencies_ms": [1e3 * x for x in r["latencies_s"]],
            "errors": r["errors"],
            "bad": r["bad"],
            "per_spindle": r["per_spindle"],
        }

    def _fail(self, what: str) -> None:
        self.proc.kill()
        _out, err = self.proc.communicate()
        raise RuntimeError(f"the OPC UA readers {what}: {err[-2000:]}")


def _rest_load(base: str, ids: list[str], args: argparse.Namespace) -> dict[str, Any]:
    """Open-loop GET ``/api/v1/spindles/{id}/compensation`` (request i to spindle i mod N)."""
    lat, statuses = asyncio.run(
        _rest(base, ids, rate=args.rate, duration_s=args.duration, conns=args.rest_clients)
    )
    ms = [1e3 * x for x in lat]
    return {
        "requests": len(ms),
        "errors": sum(c for s, c in statuses.items() if s != 200),
        "statuses": {str(s): c for s, c in statuses.items()},
        "p50_ms": percentile(ms, 50),
        "p99_ms": percentile(ms, 99),
    }


async def _rest(
    base: str, ids: list[str], *, rate: float, duration_s: float, conns: int
) -> tuple[list[float], dict[int, int]]:
    """REST GET ``/api/v1/spindles/{id}/compensation`` at ``rate``, request i to spindle i mod N: the API
    bench's open-loop load (``benchmarks._api_load._load``); the latencies [s] and the statuses."""
    from benchmarks._api_load import _load

    paths = [f"{base}/api/v1/spindles/{sid}/compensation" for sid in ids]
    records: list[tuple[float, float]] = []
    out = await _load(
        paths[0], rate=rate, duration_s=duration_s, clients=conns, kind="raw", records=records, rotate=paths
    )
    return [lat for _, lat in records], dict(out["statuses"])


@contextlib.contextmanager
def _hogs(k: int) -> Iterator[None]:
    """``k`` busy-loop processes (one per core) for the hog phase."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(k)]
    say(f"CPU hog: {k} busy-loop processes")
    try:
        time.sleep(1.0)  # they are running before the load starts
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _brief(phase: dict[str, Any]) -> str:
    q = phase["quiet"]
    reads = q.get("opcua", {}).get("latencies_ms", [])
    read = f", read p99 {percentile(reads, 99):.1f} ms" if reads else ""
    return f"REST p99 {q['rest']['p99_ms']:.1f} ms{read}"


def _bad(phases: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for p in phases:
        for path, k in p["bad"].items():
            out[path] = out.get(path, 0) + k
    return out


def _figures(
    n: int,
    ids: list[str],
    offs: list[dict[str, Any]],
    ons: list[dict[str, Any]],
    args: argparse.Namespace,
    *,
    utc: str,
    load_before: float,
) -> dict[str, Any]:
    reads = [x for r in ons for x in r["quiet"]["opcua"]["latencies_ms"]]
    hog = [r["hog"] for r in ons if "hog" in r]
    hog_reads = [x for h in hog for x in h["opcua"]["latencies_ms"]]
    check = next((r["equal_to_rest"] for r in ons if "equal_to_rest" in r), None)
    per_spindle = dict.fromkeys(ids, 0)
    for r in ons:
        for sid, k in r["quiet"]["opcua"]["per_spindle"].items():
            per_spindle[sid] += k
    rest_on = [r["quiet"]["rest"]["p99_ms"] for r in ons]
    rest_off = [r["quiet"]["rest"]["p99_ms"] for r in offs]
    out: dict[str, Any] = {
        "spindles": n,
        "clients": args.clients,
        "read_rate_per_client": args.read_rate,
        "nodes_per_read": 10,
        "utc": utc,
        "read_p50_ms": percentile(reads, 50),
        "read_p99_ms": percentile(reads, 99),
        "read_max_ms": max(reads) if reads else None,
        "read_p99_ms_per_run": [percentile(r["quiet"]["opcua"]["latencies_ms"], 99) for r in ons],
        "read_p50_ms_hog": percentile(hog_reads, 50),
        "read_p99_ms_hog": percentile(hog_reads, 99),
        "rest_p99_ms_outlets_off": median_or_none(rest_off),
        "rest_p99_ms_outlets_on": median_or_none(rest_on),
        "rest_p99_ratio_outlets_on": rest_ratio(rest_on, rest_off),
        "rest_p99_ms_per_run": {"off": rest_off, "on": rest_on},
        "rest_p99_ms_hog": median_or_none(h["rest"]["p99_ms"] for h in hog),
        "samples": {
            "reads_quiet": len(reads),
            "reads_hog": len(hog_reads),
            "reads_per_spindle": per_spindle,
            "rest_off": sum(r["quiet"]["rest"]["requests"] for r in offs),
            "rest_on": sum(r["quiet"]["rest"]["requests"] for r in ons),
            "rest_hog": sum(h["rest"]["requests"] for h in hog),
        },
        "read_errors": sum(r["quiet"]["opcua"]["errors"] for r in ons)
        + sum(h["opcua"]["errors"] for h in hog),
        "bad_values_by_node": _bad([r["quiet"]["opcua"] for r in ons] + [h["opcua"] for h in hog]),
        "rest_errors": sum(r["quiet"]["rest"]["errors"] for r in (*offs, *ons)),
        "equal_to_rest": None if check is None else check["equal"],
        "equal_to_rest_detail": check,
        "runs": args.runs,
        "duration_s": args.duration,
        "rest_rate": args.rate,
        "hog_processes": os.cpu_count(),
        "cpus": os.cpu_count(),
        "load_avg_1m_before": load_before,
        "load_avg_1m_after": os.getloadavg()[0],
    }
    out["verdicts"] = [
        {"bar": f"{key} <= {bar:g}", "value": out[key], "met": out[key] is not None and out[key] <= bar}
        for key, bar in BARS.items()
    ] + [{"bar": "equal_to_rest", "value": out["equal_to_rest"], "met": out["equal_to_rest"] is True}]
    return out
