"""``python -m benchmarks opcua``: OPC UA read and subscription latency with 10 PLC-like clients, and what the
OPC UA (and MQTT) outlets cost the REST API (issue 28, "Bars").

Set-up (all on loopback; figures, not assertions):

- the **server** is a subprocess: the real service (``simulator.served``: the demo plan through the real
  core and shell on SQLite, two identifications, a configured zero so ``/compensation`` is usable), fed the
  plan's next sample every ``--feed-period`` wall seconds, serving REST (the REST outlet, as ``chtc run``)
  and, in the "on" phase, the OPC UA outlet (and MQTT when available: ``--mqtt``; to a Mosquitto the bench
  starts on its own loopback port). It prints the wall time
  at which it hands each sample to the service.
- the **OPC UA clients** are a second subprocess (so their CPU is not the REST clients'): ``--clients``
  asyncua clients, each reading the compensation values (``Status.Usable``, ``Status.Heartbeat``,
  ``Status.SampleAge``, the axial growth and its CI, the controller values: 10 nodes in one Read, as a PLC's
  ``OPC_UA_ReadList``) ``--read-rate`` times a second, open loop, and one subscriber on
  ``Status.NewestSampleTime`` (publishing interval 100 ms). Read latency is send to response;
  subscription latency is from the server's hand-over of a sample to the service to the notification
  carrying that sample's time.
- the **REST load** runs in this process: GET /api/v1/chtc at ``--rate`` over ``--rest-clients`` keep-alive
  connections (``benchmarks.api``'s raw client), in both phases; the "off" phase runs the same server
  without the OPC UA and MQTT outlets. The phases alternate ``--runs`` times; medians are quoted.
  ``rest_p99_ratio_outlets_on`` = REST p99 with the outlets on / off, same invocation.

``--spindles N`` with N > 1: the hosted server (one OPC UA server, one object per spindle) of N simulated
spindles started as ``python -m benchmarks fleet`` starts them, REST ``/api/v1/spindles/{id}/compensation``,
a CPU-hog phase and every spindle compared with REST: ``benchmarks.opcua_host``. ``--spindles 1`` (the
default) is the bench above.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.opcua_figures import COMPENSATION_NODES

ROOT = Path(__file__).resolve().parents[1]  # benchmarks/ is not installed: its children import it from here
TARGET_READ_P99_MS = 10.0
TARGET_REST_RATIO = 1.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--clients", type=int, default=10, help="OPC UA clients reading concurrently")
    parser.add_argument("--read-rate", type=float, default=10.0, help="reads per second per OPC UA client")
    parser.add_argument("--rate", type=float, default=50.0, help="REST GET /chtc per second")
    parser.add_argument("--rest-clients", type=int, default=2, help="REST keep-alive connections")
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        help="seconds of load per phase (default: 10; 20 with --spindles N > 1)",
    )
    parser.add_argument(
        "--runs",
        type=int,
        default=None,
        help="off/on phase pairs; medians are quoted (default: 2; 3 with N > 1)",
    )
    parser.add_argument(
        "--spindles",
        default="1",
        help="comma-separated N: N > 1 hosts N simulated spindles as 'benchmarks fleet' does (one OPC UA "
        "server, one object per spindle; PostgreSQL at --pg-url; REST /api/v1/spindles/{id}/compensation, "
        "a CPU-hog phase, every spindle compared with REST): benchmarks.opcua_host",
    )
    parser.add_argument(
        "--settle", type=float, default=15.0, help="N > 1: s after every /compensation answers, before loads"
    )
    parser.add_argument("--pg-url", default=None, help="N > 1: PostgreSQL (default: benchmarks fleet's)")
    parser.add_argument("--plants", type=int, default=4, help="N > 1: distinct duty cycles the devices play")
    parser.add_argument("--feed-period", type=float, default=1.0, help="wall s between fed samples")
    parser.add_argument(
        "--mqtt",
        choices=("auto", "on", "off"),
        default="auto",
        help="the MQTT outlet in the 'on' phase: auto = when the settings know it and a broker answers on "
        "127.0.0.1:1883",
    )


# --- the server subprocess --------------------------------------------------------------------------------
def serve(config: str) -> None:
    """Entry point of the server subprocess: ``config`` is JSON {rest_port, opcua_port (0: off), mqtt,
    feed_period_s}. Prints {"ready": ...} then {"fed": iso, "wall": s} per sample on stdout."""
    import tempfile
    from pathlib import Path

    from service.serve.outlet import OutletContext, load_factory
    from service.settings import Settings
    from simulator.served import DEMO_FED, exit_on_sigterm, served_service

    cfg = json.loads(config)
    exit_on_sigterm()
    sections: dict[str, Any] = {
        "api": {"host": "127.0.0.1", "port": cfg["rest_port"]},
        "compensation": {"reference_c": 20.0},
        # per condition: no identification is due in the fed samples (the 4000 rpm condition's 11-16th
        # minute), so no job competes for this process's CPU (the real service runs jobs in another process)
        "identification": {"mode": "per_condition"},
    }
    if cfg["opcua_port"]:
        sections["opcua"] = {
            "enabled": True,
            "port": cfg["opcua_port"],
            "max_connections": cfg["max_connections"],
            "spindle": "Spindle1",  # the NodeIds the readers use (unset: spindle.id)
        }
    state = tempfile.TemporaryDirectory(prefix="chtc-bench-mqtt-")  # the Sparkplug bdSeq file
    if cfg["mqtt"]:
        mqtt = {"enabled": True, "host": "127.0.0.1", "port": cfg["mqtt"], "state_dir": state.name}
        sections["mqtt"] = mqtt
    settings = Settings(**sections)
    sys.setswitchinterval(settings.engine.gil_switch_interval_s)  # as Runtime.start does
    names = ["rest"] + (["opcua"] if cfg["opcua_port"] else []) + (["mqtt"] if cfg["mqtt"] else [])
    with (
        state,
        tempfile.TemporaryDirectory(prefix="chtc-bench-opcua-") as tmp,
        served_service(
            database_url=f"sqlite:///{Path(tmp) / 'chtc.db'}", settings=settings, feed_samples=DEMO_FED
        ) as served,
    ):
        outlets = []
        for name in names:
            outlet = load_factory(name)(
                OutletContext(settings=settings, service=served.service, clock=served.clock)
            )
            served.call(outlet.start)
            served.service.subscribe(outlet)
            outlets.append(outlet)
        deadline = time.monotonic() + 60.0
        while not all(getattr(o, "started", True) for o in outlets):  # uvicorn listens (the REST outlet)
            if time.monotonic() > deadline:
                raise RuntimeError("the REST outlet did not start listening within 60 s")
            time.sleep(0.05)
        print(json.dumps({"ready": names}), flush=True)
        try:
            while served.fed < len(served.samples):
                time.sleep(cfg["feed_period_s"])
                s = served.samples[served.fed]
                print(json.dumps({"fed": s.t.isoformat(), "wall": time.time()}), flush=True)
                _hand_over(served, s)
            time.sleep(3600.0)  # the plan ran out: keep serving until terminated
        finally:
            for outlet in reversed(outlets):
                served.call(outlet.close)


def _hand_over(served: Any, sample: Any) -> None:
    """As the acquisition does: ``on_sample`` on the service's loop, not waiting for the jobs it may start."""
    served.fed += 1
    served.clock.at_least(sample.t)

    async def deliver() -> None:
        served.service.on_sample(sample)

    served.call(deliver)


class Server:
    """The server subprocess and the wall times of its fed samples (a reader thread)."""

    def __init__(self, *, opcua: bool, mqtt: int, feed_period_s: float, clients: int) -> None:
        self.rest_port = _free_port()
        self.opcua_port = _free_port() if opcua else 0
        cfg = {
            "rest_port": self.rest_port,
            "opcua_port": self.opcua_port,
            "mqtt": mqtt,
            "feed_period_s": feed_period_s,
            "max_connections": clients + 2,  # the readers and the subscriber
        }
        code = f"from benchmarks.opcua import serve; serve({json.dumps(cfg)!r})"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
        )
        self.fed: dict[str, float] = {}
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()
        if not self.ready.wait(180.0) or self.proc.poll() is not None:
            err = self.proc.stderr.read()[-3000:] if self.proc.stderr and self.proc.poll() is not None else ""
            self.stop()
            raise RuntimeError(f"the bench server did not start: {err}")

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.rest_port}"

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.opcua_port}/chtc"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            msg = json.loads(line) if line.startswith("{") else {}
            if "ready" in msg:
                self.ready.set()
            elif "fed" in msg:
                self.fed[msg["fed"]] = float(msg["wall"])
        self.ready.set()

    def stop(self) -> None:
        from benchmarks._api_phases import stop_process

        stop_process(self.proc)


# --- the OPC UA clients' subprocess -------------------------------------------------------------------------
def readers(config: str) -> None:
    """Entry point of the OPC UA clients' subprocess: prints one JSON result (see the module docstring)."""
    cfg = json.loads(config)
    print(json.dumps(asyncio.run(_readers(cfg))), flush=True)


async def _readers(cfg: dict[str, Any]) -> dict[str, Any]:
    from asyncua import Client, ua

    clients = [Client(cfg["endpoint"], timeout=10) for _ in range(cfg["clients"] + 1)]
    for c in clients:
        await c.connect()
    idx = await clients[0].get_namespace_index("urn:spindle-chtc:opcua")
    notes: list[tuple[str, float]] = []

    class Handler:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            if isinstance(val, datetime):
                notes.append((val.isoformat(), time.time()))

    sub = await clients[-1].create_subscription(100, Handler())
    await sub.subscribe_data_change(clients[-1].get_node(f"ns={idx};s=Spindle1.Status.NewestSampleTime"))
    loop = asyncio.get_running_loop()
    lat: list[float] = []
    errors = 0
    rate, duration = float(cfg["read_rate"]), float(cfg["duration_s"])
    t0 = loop.time() + 0.2

    async def reader(k: int, c: Client) -> None:
        nonlocal errors
        nodes = [c.get_node(f"ns={idx};s=Spindle1.{p}") for p in COMPENSATION_NODES]
        n = int(rate * duration)
        for i in range(n):
            due = t0 + (i + k / len(clients)) / rate
            if (delay := due - loop.time()) > 0:
                await asyncio.sleep(delay)
            start = time.perf_counter()
            try:
                values = await c.read_attributes(nodes, ua.AttributeIds.Value)
                errors += sum(not v.StatusCode_.is_good() and v.StatusCode_.value >> 30 == 2 for v in values)
            except Exception:
                errors += 1
            lat.append(time.perf_counter() - start)

    await asyncio.gather(*(reader(k, c) for k, c in enumerate(clients[:-1])))
    await sub.delete()
    for c in clients:
        await c.disconnect()
    return {"latencies_s": lat, "errors": errors, "notifications": notes}


def _run_readers(endpoint: str, args: argparse.Namespace) -> dict[str, Any]:
    cfg = {
        "endpoint": endpoint,
        "clients": args.clients,
        "read_rate": args.read_rate,
        "duration_s": args.duration,
    }
    code = f"from benchmarks.opcua import readers; readers({json.dumps(cfg)!r})"
    timeout = 120 + 3 * args.duration
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, cwd=ROOT
    )
    lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"the OPC UA clients failed: {proc.stderr[-3000:]}")
    return dict(json.loads(lines[-1]))


# --- phases -------------------------------------------------------------------------------------------------
def _rest(url: str, args: argparse.Namespace) -> dict[str, Any]:
    """The REST load; also the API's own p99 of the same requests (its latency histogram, scraped around)."""
    from benchmarks._api_load import _load, _server_buckets, histogram_quantile

    before = _server_buckets(url)
    out = asyncio.run(
        _load(
            url + "/api/v1/chtc",
            rate=args.rate,
            duration_s=args.duration,
            clients=args.rest_clients,
            kind="raw",
        )
    )
    p99 = histogram_quantile(0.99, before, _server_buckets(url))
    out["server_p99_ms"] = None if p99 is None else 1e3 * p99
    return out


def _phase(args: argparse.Namespace, *, on: bool, mqtt: int) -> dict[str, Any]:
    server = Server(opcua=on, mqtt=mqtt if on else 0, feed_period_s=args.feed_period, clients=args.clients)
    try:
        out: dict[str, Any] = {}
        if not on:
            out["rest"] = _rest(server.url, args)
            return out
        box: dict[str, Any] = {}
        t = threading.Thread(target=lambda: box.update(_run_readers(server.endpoint, args)), daemon=True)
        t.start()
        time.sleep(2.0)  # the clients connect (not measured) before the REST load starts
        out["rest"] = _rest(server.url, args)
        t.join(120.0 + 3 * args.duration)
        if "latencies_s" not in box:
            raise RuntimeError("the OPC UA clients did not report")
        sub = [1e3 * (wall - server.fed[v]) for v, wall in box["notifications"] if v in server.fed]
        out["opcua"] = {
            "latencies_ms": [1e3 * x for x in box["latencies_s"]],
            "errors": box["errors"],
            "sub_ms": sub,
        }
        return out
    finally:
        server.stop()


def _p(xs: list[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(xs), q)) if xs else None


def run_bench(args: argparse.Namespace) -> dict[str, Any]:
    want_mqtt = _mqtt_available() if args.mqtt == "auto" else args.mqtt == "on"
    broker = Broker() if want_mqtt else None
    offs, ons = [], []
    try:
        mqtt = broker.port if broker is not None else 0
        for _ in range(args.runs):
            offs.append(_phase(args, on=False, mqtt=0))
            ons.append(_phase(args, on=True, mqtt=mqtt))
    finally:
        if broker is not None:
            broker.stop()
    reads = [x for r in ons for x in r["opcua"]["latencies_ms"]]
    subs = [x for r in ons for x in r["opcua"]["sub_ms"]]
    rest_off = statistics.median(r["rest"]["p99_ms"] for r in offs)
    rest_on = statistics.median(r["rest"]["p99_ms"] for r in ons)
    server_off = _median([r["rest"]["server_p99_ms"] for r in offs])
    server_on = _median([r["rest"]["server_p99_ms"] for r in ons])
    read_p99 = _p(reads, 99)
    ratio = rest_on / rest_off if rest_off > 0 else None
    return {
        "clients": args.clients,
        "read_rate_per_client": args.read_rate,
        "nodes_per_read": len(COMPENSATION_NODES),
        "reads": len(reads),
        "read_errors": sum(r["opcua"]["errors"] for r in ons),
        "read_p50_ms": _p(reads, 50),
        "read_p99_ms": read_p99,
        "read_max_ms": max(reads) if reads else None,
        "notifications": len(subs),
        "subscription_latency_ms_p50": _p(subs, 50),
        "subscription_latency_ms_p99": _p(subs, 99),
        "rest_rate": args.rate,
        "rest_p99_ms_outlets_off": rest_off,
        "rest_p99_ms_outlets_on": rest_on,
        "rest_p99_ratio_outlets_on": ratio,
        "rest_server_p99_ms_outlets_off": server_off,
        "rest_server_p99_ms_outlets_on": server_on,
        "rest_server_p99_ratio_outlets_on": None
        if not server_off or server_on is None
        else server_on / server_off,
        "rest_p99_ms_per_run": {
            "off": [r["rest"]["p99_ms"] for r in offs],
            "on": [r["rest"]["p99_ms"] for r in ons],
        },
        "rest_errors": sum(r["rest"]["errors"] for r in (*offs, *ons)),
        "outlets_on": ["rest", "opcua", *(["mqtt"] if want_mqtt else [])],
        "runs": args.runs,
        "duration_s": args.duration,
        "cpus": os.cpu_count(),
        "load_avg_1m": os.getloadavg()[0],
        "meets_read_p99": None if read_p99 is None else read_p99 <= TARGET_READ_P99_MS,
        "meets_rest_ratio": None if ratio is None else ratio <= TARGET_REST_RATIO,
    }


def _median(xs: list[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return statistics.median(vals) if vals else None


MOSQUITTO = "/usr/sbin/mosquitto"


def _mqtt_available() -> bool:
    """The settings know an MQTT outlet and Mosquitto is installed (the bench starts its own broker)."""
    import shutil

    from service.settings import Settings

    installed = shutil.which("mosquitto") is not None or os.path.exists(MOSQUITTO)
    return "mqtt" in Settings.model_fields and installed


class Broker:
    """A Mosquitto of the bench's own on a free loopback port (never the machine's shared one)."""

    def __init__(self) -> None:
        import shutil
        import tempfile

        self.port = _free_port()
        self.dir = tempfile.mkdtemp(prefix="chtc-bench-broker-")
        conf = os.path.join(self.dir, "mosquitto.conf")
        with open(conf, "w", encoding="utf-8") as f:
            f.write(f"user root\nallow_anonymous true\nlistener {self.port} 127.0.0.1\n")
        exe = shutil.which("mosquitto") or MOSQUITTO
        self.proc = subprocess.Popen([exe, "-c", conf], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10.0
        while True:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    self.stop()
                    raise RuntimeError("mosquitto did not start") from None
                time.sleep(0.05)

    def stop(self) -> None:
        from benchmarks._api_phases import stop_process

        stop_process(self.proc)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _hosted_main(ns: list[int], args: argparse.Namespace) -> int:
    """``--spindles N[,M]`` with a hosted N: ``benchmarks.opcua_host``; N = 1 in the list runs as before."""
    from benchmarks.fleet_host import DEFAULT_PG
    from benchmarks.opcua_host import run_host_bench

    if args.pg_url is None:
        args.pg_url = DEFAULT_PG
    results = [run_bench(args) if n == 1 else run_host_bench(n, args) for n in ns]
    if args.json:
        print(json.dumps(results[0] if len(results) == 1 else {"runs": results}, indent=2))
        return 0
    for r in results:
        if r.get("spindles", 1) == 1:
            continue
        print(
            f"N={r['spindles']}: {r['clients']} clients x {r['read_rate_per_client']:g} reads/s: read p50 "
            f"{_fmt(r['read_p50_ms'])} ms, p99 {_fmt(r['read_p99_ms'])} ms; beside a CPU hog p99 "
            f"{_fmt(r['read_p99_ms_hog'])} ms; REST /compensation p99 "
            f"{_fmt(r['rest_p99_ms_outlets_off'])} -> "
            f"{_fmt(r['rest_p99_ms_outlets_on'])} ms (ratio {_fmt(r['rest_p99_ratio_outlets_on'])}); "
            f"equal to REST: {r['equal_to_rest']}"
        )
        for v in r["verdicts"]:
            print(f"  {'met   ' if v['met'] else 'MISSED'} {v['bar']} (measured {v['value']})")
    return 0


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def main(args: argparse.Namespace) -> int:
    ns = sorted({int(x) for x in str(args.spindles).split(",") if x.strip()})
    hosted = [n for n in ns if n > 1]
    args.duration = args.duration if args.duration is not None else (20.0 if hosted else 10.0)
    args.runs = args.runs if args.runs is not None else (3 if hosted else 2)
    if hosted:
        return _hosted_main(ns, args)
    r = run_bench(args)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    lines = [
        f"OPC UA: {r['clients']} clients x {r['read_rate_per_client']:g} reads/s of "
        f"{r['nodes_per_read']} nodes",
        f"  read p50 {_fmt(r['read_p50_ms'])} ms, p99 {_fmt(r['read_p99_ms'])} ms "
        f"(target <= {TARGET_READ_P99_MS:g})",
        f"  subscription: {r['notifications']} notifications, "
        f"p50 {_fmt(r['subscription_latency_ms_p50'])} ms, p99 {_fmt(r['subscription_latency_ms_p99'])} ms "
        "(sample handed over -> notification)",
        f"REST /chtc p99: {_fmt(r['rest_p99_ms_outlets_off'])} ms off, "
        f"{_fmt(r['rest_p99_ms_outlets_on'])} ms with {'+'.join(r['outlets_on'])}: "
        f"ratio {_fmt(r['rest_p99_ratio_outlets_on'])} (target <= {TARGET_REST_RATIO:g})",
    ]
    print("\n".join(lines))
    return 0
