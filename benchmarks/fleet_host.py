"""``python -m benchmarks fleet --spindles 10,50``: N spindles hosted as the product hosts them, at their real
rates, writing into one PostgreSQL (issue 29, item 8; docs/design/fleet.md).

For each N (and N = 1 first, the baseline the per-spindle figures are taken against):

1. a fresh schema in the PostgreSQL of ``--pg-url``;
2. the devices of N spindles in a child process (``simulator.fleetrig``): N Modbus DAQs and N CAN nodes
   behind N python-can-remote hubs, at real rate, playing virtual-plant duty cycles;
3. the product: ``chtc run --config host.toml --migrate``, a real process with one ``[[spindles]]`` entry
   each (shared model, identification pool, engines; its REST server on a free port);
4. after ``--warmup-s``, a window of ``--window-s``: the product's CPU (its process and the pool's, from
   /proc), its memory (RSS of both, at the end), the database writes' latency (``chtc_db_write_seconds``
   from its /metrics, the window's difference), its connections (``pg_stat_activity`` by application
   name), and the rows each table gained per spindle-day.

``mib_per_added_spindle`` = (RSS(N) − RSS(N')) / (N − N'), N' the previous N (the first: 1);
``cpu_pct_per_spindle`` = CPU(N) / wall / N (the
steady share, identifications included; the pool's processes count). ``bytes_per_spindle_day`` = the rows
each table gained per spindle-day in the window (what the hosted product really writes: samples, minute
means, conditions, identifications, events) × that table's bytes per row at a day's scale
(``python -m benchmarks storage``'s synthetic day through the same write path; a few minutes of rows in fresh
partitions would measure mostly empty pages).

The devices' process is not the product's and is not counted. On a plant the devices are other hardware;
here they run at nice 10 on the last core and the product on the others (``taskset``), so on 2 cores the
product gets one core. PostgreSQL floats over both; the load average is reported.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.host.runtime import free_port

__all__ = [
    "BARS",
    "DEFAULT_PG",
    "OUTLETS",
    "Outlets",
    "measure_fleet",
    "p99_of",
    "parse_outlets",
    "refused_by_host",
    "run_n",
]

# the benches' PostgreSQL (a role with CREATE DATABASE rights)
DEFAULT_PG = os.environ.get("CHTC_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
BARS = {"write_p99_ms": 50.0, "mib_per_added_spindle": 60.0, "cpu_pct_per_spindle": 2.0}
DEVICES_NICE = 10
# On a plant the devices are other hardware: here, with 2 cores or more, they get the last core and the
# product the others (PostgreSQL floats), so the devices' 100 frames/s per spindle cannot take its core
_CPUS = os.cpu_count() or 1
DEVICES_CPUS = f"{_CPUS - 1}" if _CPUS >= 2 else None
PRODUCT_CPUS = f"0-{_CPUS - 2}" if _CPUS >= 2 else None


def pin(cpus: str | None) -> list[str]:
    """``taskset -c CPUS`` as a command prefix (none with one core or without taskset)."""
    import shutil

    return ["taskset", "-c", cpus] if cpus is not None and shutil.which("taskset") else []


_TICKS = os.sysconf("SC_CLK_TCK")
_PAGE_MIB = os.sysconf("SC_PAGE_SIZE") / 2**20


def say(msg: str) -> None:
    print(f"bench fleet: {msg}", file=sys.stderr, flush=True)


# --- /proc ------------------------------------------------------------------------------------------
def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()  # fields from the 3rd (state) on


def children(pid: int) -> list[int]:
    """Live child processes of ``pid`` (the identification pool's)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            st = _stat(int(entry.name))
            if st is not None and int(st[1]) == pid:
                out.append(int(entry.name))
    return out


def cpu_s(pid: int) -> float:
    """CPU seconds of ``pid`` and its live children (user + system, and reaped children's)."""
    total = 0.0
    for p in (pid, *children(pid)):
        st = _stat(p)
        if st is not None:
            total += sum(int(x) for x in st[11:15]) / _TICKS  # utime, stime, cutime, cstime
    return total


def rss_mib(pid: int, *, with_children: bool = True) -> float:
    total = 0.0
    for p in (pid, *children(pid)) if with_children else (pid,):
        st = _stat(p)
        if st is not None:
            total += int(st[21]) * _PAGE_MIB  # rss, pages
    return total


# --- /metrics ---------------------------------------------------------------------------------------
_BUCKET = re.compile(r"^chtc_db_write_seconds_bucket\{([^}]*)\} ([0-9.eE+-]+)$", re.M)


def write_buckets(metrics_text: str) -> dict[float, float]:
    """Cumulative counts per upper bound (s), summed over the spindles."""
    out: dict[float, float] = {}
    for labels, value in _BUCKET.findall(metrics_text):
        le = re.search(r'le="([^"]+)"', labels)
        if le is not None:
            bound = float("inf") if le.group(1) == "+Inf" else float(le.group(1))
            out[bound] = out.get(bound, 0.0) + float(value)
    return out


def p99_of(before: dict[float, float], after: dict[float, float], q: float = 0.99) -> float | None:
    """The q-quantile (s) of the observations between two scrapes of a cumulative histogram, interpolated
    linearly inside its bucket (Prometheus' histogram_quantile); None without observations."""
    bounds = sorted(after)
    counts = [after[b] - before.get(b, 0.0) for b in bounds]
    total = counts[-1] if counts else 0.0
    if total <= 0:
        return None
    rank = q * total
    prev_b, prev_c = 0.0, 0.0
    for b, c in zip(bounds, counts, strict=True):
        if c >= rank:
            if b == float("inf"):
                return prev_b
            return prev_b + (b - prev_b) * (rank - prev_c) / max(c - prev_c, 1e-12)
        prev_b, prev_c = b, c
    return bounds[-2] if len(bounds) > 1 else None


# --- PostgreSQL -------------------------------------------------------------------------------------
@contextlib.contextmanager
def fresh_schema(pg_url: str) -> Iterator[tuple[str, str, Any]]:
    """(schema, url for the product with search_path and application_name, admin engine)."""
    import sqlalchemy as sa
    from sqlalchemy.engine import make_url

    schema = f"chtc_fleet_{uuid.uuid4().hex[:10]}"
    app = f"chtc-bench-{schema}"
    admin = sa.create_engine(pg_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    url = make_url(pg_url).update_query_dict({"options": f"-csearch_path={schema}", "application_name": app})
    try:
        yield schema, url.render_as_string(hide_password=False), admin
    finally:
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def table_rows(admin: Any, schema: str) -> dict[str, int]:
    """Rows per table of the schema (``samples``: its partitions through the parent)."""
    import sqlalchemy as sa

    from benchmarks.storage import TABLES

    out = {}
    with admin.connect() as conn:
        present = {
            r[0]
            for r in conn.execute(
                sa.text("SELECT tablename FROM pg_tables WHERE schemaname = :s"), {"s": schema}
            )
        }
        for t in TABLES:
            if t in present:
                out[t] = int(conn.execute(sa.text(f'SELECT count(*) FROM "{schema}"."{t}"')).scalar_one())
    return out


def day_bytes_per_row(pg_url: str) -> dict[str, float]:
    """Bytes per row of each table at the scale of a spindle-day (``python -m benchmarks storage``'s synthetic
    day, through the product's write path: heap, indexes and TOAST of a day's partition)."""
    from benchmarks.storage import per_spindle_day

    after = per_spindle_day(pg_url, 150)["after"]
    return {t: size / rows for t, (rows, size) in after.items() if rows > 0}


def connections(admin: Any, schema: str) -> int:
    import sqlalchemy as sa

    with admin.connect() as conn:
        value = conn.execute(
            sa.text("SELECT count(*) FROM pg_stat_activity WHERE application_name = :a"),
            {"a": f"chtc-bench-{schema}"},
        ).scalar_one()
    return int(value)


# --- one N ------------------------------------------------------------------------------------------
OUTLETS = ("opcua", "mqtt")


@dataclass(frozen=True)
class Outlets:
    """The protocol outlets the hosted product serves for every spindle, beside REST (``--outlets``): the
    port of each (0: off). MQTT needs a broker: ``mqtt_port`` is the bench's own Mosquitto's."""

    opcua_port: int = 0
    mqtt_port: int = 0
    state_dir: str = ""  # [mqtt] state_dir (the Sparkplug bdSeq file)
    max_connections: int = 10  # [opcua] max_connections

    def flags(self) -> dict[str, bool]:
        """The JSON key saying which outlets were on, e.g. {"opcua": true, "mqtt": false}."""
        return {"opcua": self.opcua_port > 0, "mqtt": self.mqtt_port > 0}


def parse_outlets(text: str) -> frozenset[str]:
    """``--outlets opcua,mqtt`` as a set of names ('' or 'none': none); ValueError on an unknown name."""
    names = {x.strip().lower() for x in text.split(",") if x.strip()} - {"none"}
    unknown = sorted(names - set(OUTLETS))
    if unknown:
        raise ValueError(f"--outlets: unknown {', '.join(unknown)} (known: {', '.join(OUTLETS)}, none)")
    return frozenset(names)


def host_toml(
    url: str, api_port: int, modbus_ports: list[int], can_ports: list[int], outlets: Outlets | None = None
) -> str:
    lines = [
        "[api]",
        f"port = {api_port}",
        "[database]",
        f"url = {json.dumps(url)}",
    ]
    o = outlets or Outlets()
    if o.opcua_port:
        lines += [
            "[opcua]",
            "enabled = true",
            f"port = {o.opcua_port}",
            f"max_connections = {o.max_connections}",
        ]
    if o.mqtt_port:
        lines += ["[mqtt]", "enabled = true", 'host = "127.0.0.1"', f"port = {o.mqtt_port}"]
        lines += [f"state_dir = {json.dumps(o.state_dir)}"] if o.state_dir else []
    for i, (m, c) in enumerate(zip(modbus_ports, can_ports, strict=True)):
        lines += [
            "[[spindles]]",
            f'id = "bench-{i + 1:03d}"',
            f"modbus = {{ port = {m} }}",
            f'can = {{ interface = "remote", channel = "ws://127.0.0.1:{c}/" }}',
        ]
    return "\n".join(lines) + "\n"


def refused_by_host(config: Path) -> str | None:
    """What the host says when it refuses these settings at start (e.g. ``[mqtt]`` with ``[[spindles]]``
    before MQTT is hosted): its message, naming the setting; None when it takes them. Checked here, before
    any process starts, through the product's own ``Host`` (no I/O in its constructor)."""
    from service.host.fleet import Host, HostError
    from service.host.runtime import ScaledClock
    from service.settings import load_settings

    settings = load_settings(config)
    try:
        Host(settings=settings, clock=ScaledClock(1.0), devices=lambda s: None, on_event=lambda m: None)  # type: ignore[arg-type, return-value]
    except HostError as err:
        return str(err)
    return None


def _get(url: str, timeout_s: float = 5.0) -> tuple[int, str]:
    import httpx

    try:
        r = httpx.get(url, timeout=timeout_s)
    except httpx.HTTPError:
        return 0, ""
    return r.status_code, r.text


def _wait(pred: Any, timeout_s: float, what: str, proc: subprocess.Popen[bytes] | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"{what}: the process exited with code {proc.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.5)


@dataclass(frozen=True)
class _Snapshot:
    """What the window's figures are differences of, read at its start and at its end."""

    writes: dict[float, float]  # chtc_db_write_seconds buckets, cumulative (``write_buckets``)
    cpu_s: float  # the product's and its pool's CPU seconds (``cpu_s``)
    rows: dict[str, int]  # rows per table (``table_rows``)
    t: float  # time.monotonic(), s


def _snapshot(base: str, pid: int, admin: Any, schema: str) -> _Snapshot:
    return _Snapshot(
        writes=write_buckets(_get(f"{base}/metrics")[1]),
        cpu_s=cpu_s(pid),
        rows=table_rows(admin, schema),
        t=time.monotonic(),
    )


def _env() -> dict[str, str]:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def devices(n: int, *, plants: int, hours: float) -> Iterator[tuple[list[int], list[int]]]:
    """The devices of N spindles (``simulator.fleetrig``, nice 10, pinned): (Modbus ports, CAN hub ports)."""
    plan = {"host": "127.0.0.1", "spindles": n, "plants": plants, "hours": round(hours, 3)}
    say(f"N={n}: devices (plants: {min(plants, n)} × {hours:.2f} h)")
    rig = subprocess.Popen(
        # at nice 10: on a plant the devices are other hardware; here they must not take the cores the product
        # and the database need (at N = 50 they send 5 000 CAN frames/s through 50 websocket hubs)
        [
            *pin(DEVICES_CPUS),
            "nice",
            "-n",
            str(DEVICES_NICE),
            sys.executable,
            "-m",
            "simulator.fleetrig",
            json.dumps(plan),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=_env(),
    )
    try:
        assert rig.stdout is not None
        line = rig.stdout.readline().decode().strip()
        if not line.startswith("ready "):
            raise RuntimeError(f"the devices' process did not start (said {line!r}, code {rig.poll()})")
        ports = json.loads(line.removeprefix("ready "))
        yield ports["modbus_ports"], ports["can_ports"]
    finally:
        _stop(rig)


@contextlib.contextmanager
def product(config: Path, log_path: Path, api_port: int) -> Iterator[subprocess.Popen[bytes]]:
    """``chtc run --config CONFIG --migrate`` (pinned), ready (``/readyz`` 200) when entered; then stopped."""
    with log_path.open("wb") as log:
        say(f"product (chtc run --config {config.name} --migrate)")
        proc = subprocess.Popen(
            [
                *pin(PRODUCT_CPUS),
                sys.executable,
                "-m",
                "service.cli",
                "run",
                "--config",
                str(config),
                "--migrate",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=_env(),
        )
        try:
            base = f"http://127.0.0.1:{api_port}"
            try:
                _wait(lambda: _get(f"{base}/readyz")[0] == 200, 600.0, "the product's /readyz", proc)
            except (RuntimeError, TimeoutError) as err:
                tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
                raise RuntimeError(f"{err}; its log ends: {' | '.join(tail)}") from None
            yield proc
        finally:
            _stop(proc)


def run_n(
    n: int,
    *,
    pg_url: str,
    warmup_s: float,
    window_s: float,
    plants: int,
    workdir: Path,
    row_bytes: dict[str, float],
    outlets: Outlets | None = None,
) -> dict[str, Any]:
    """One N: devices, the product (with ``outlets`` on for every spindle), the window; that run's figures."""
    hours = (warmup_s + window_s) / 3600.0 + 0.5
    with (
        devices(n, plants=plants, hours=hours) as (modbus_ports, can_ports),
        fresh_schema(pg_url) as (
            schema,
            url,
            admin,
        ),
    ):
        api_port = free_port()
        config = workdir / f"host-{n}.toml"
        config.write_text(host_toml(url, api_port, modbus_ports, can_ports, outlets), encoding="utf-8")
        with product(config, workdir / f"product-{n}.log", api_port) as proc:
            base = f"http://127.0.0.1:{api_port}"
            listed = json.loads(_get(f"{base}/api/v1/spindles")[1])["spindles"]
            running = sum(1 for s in listed if s["running"])
            say(f"N={n}: {running}/{n} spindles running; warm-up {warmup_s:g} s")
            time.sleep(warmup_s)
            w0 = _snapshot(base, proc.pid, admin, schema)
            say(f"N={n}: measuring {window_s:g} s")
            time.sleep(window_s)
            w1 = _snapshot(base, proc.pid, admin, schema)
            wall_s = w1.t - w0.t
            days = n * wall_s / 86400.0
            rows_day = {t: (w1.rows.get(t, 0) - w0.rows.get(t, 0)) / days for t in w1.rows}
            healthy, degraded = _health(base, [str(x["id"]) for x in listed])
            return {
                "spindles": n,
                "running": running,
                "outlets": (outlets or Outlets()).flags(),
                "healthy_at_end": healthy,
                "degraded_parts": degraded,
                "write_p99_ms": _ms(p99_of(w0.writes, w1.writes)),
                "writes": int(w1.writes.get(float("inf"), 0) - w0.writes.get(float("inf"), 0)),
                "rss_mib": round(rss_mib(proc.pid), 1),
                "rss_main_mib": round(rss_mib(proc.pid, with_children=False), 1),
                "pool_processes": len(children(proc.pid)),
                "cpu_pct": round(100.0 * (w1.cpu_s - w0.cpu_s) / wall_s, 2),
                "cpu_pct_per_spindle": round(100.0 * (w1.cpu_s - w0.cpu_s) / wall_s / n, 3),
                "rows_per_spindle_day": {t: round(v) for t, v in rows_day.items() if v > 0},
                "bytes_per_spindle_day": int(sum(v * row_bytes.get(t, 0.0) for t, v in rows_day.items())),
                "connections": connections(admin, schema),
                "load_average_1min": round(os.getloadavg()[0], 2),
            }


def _health(base: str, ids: list[str]) -> tuple[int, dict[str, int]]:
    """How many spindles' /healthz say ok, and which parts are not ok how often (e.g. event_loop, modbus)."""
    healthy = 0
    parts: dict[str, int] = {}
    for sid in ids:
        body = json.loads(_get(f"{base}/api/v1/spindles/{sid}/healthz")[1] or "{}")
        healthy += body.get("status") == "ok"
        for dev in body.get("devices", []):
            if dev.get("status") not in ("ok", "disabled"):
                parts[str(dev.get("name"))] = parts.get(str(dev.get("name")), 0) + 1
    return healthy, parts


def _ms(s: float | None) -> float | None:
    return None if s is None else round(1e3 * s, 2)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM, then SIGKILL after 30 s; closes its stdin (the devices' process stops at end of file)."""
    if proc.stdin is not None:
        with contextlib.suppress(OSError):
            proc.stdin.close()
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10.0)


def outlets_for(names: frozenset[str], *, mqtt_port: int, state_dir: str) -> Outlets:
    """Fresh ports for one product's outlets (``names`` from ``parse_outlets``)."""
    return Outlets(
        opcua_port=free_port() if "opcua" in names else 0,
        mqtt_port=mqtt_port if "mqtt" in names else 0,
        state_dir=state_dir,
    )


def measure_fleet(
    ns: list[int],
    *,
    pg_url: str,
    warmup_s: float,
    window_s: float,
    plants: int,
    outlets: frozenset[str] = frozenset(),
    mqtt_port: int = 0,
) -> dict[str, Any]:
    """The runs (N = 1 first as the baseline) with the per-added-spindle memory; ``outlets`` on for every
    spindle in each run (MQTT to the broker on ``mqtt_port``)."""
    say("bytes per row at a spindle-day's scale (python -m benchmarks storage's synthetic day)")
    row_bytes = day_bytes_per_row(pg_url)
    with tempfile.TemporaryDirectory(prefix="chtc-bench-fleet-") as tmp:
        kw: dict[str, Any] = {"pg_url": pg_url, "warmup_s": warmup_s, "window_s": window_s, "plants": plants}
        kw.update(workdir=Path(tmp), row_bytes=row_bytes)

        def one(n: int) -> dict[str, Any]:
            return run_n(n, outlets=outlets_for(outlets, mqtt_port=mqtt_port, state_dir=tmp), **kw)

        base = one(1)
        say(f"N=1: {json.dumps(base)}")  # each run's figures as they come (a later failure keeps them)
        runs = []
        prev = base
        for n in ns:
            r = one(n)
            # the slope from the previous N (the first: from N = 1): fixed costs (the pool, the model) cancel
            r["mib_per_added_spindle"] = round(
                (r["rss_mib"] - prev["rss_mib"]) / max(n - prev["spindles"], 1), 2
            )
            runs.append(r)
            say(f"N={n}: {json.dumps(r)}")
            prev = r
    return {
        "outlets": {name: name in outlets for name in OUTLETS},
        "baseline": base,
        "runs": runs,
        "bytes_per_row": {t: round(b, 1) for t, b in row_bytes.items()},
    }


def verdicts(runs: list[dict[str, Any]]) -> list[tuple[str, bool]]:
    """The issue's bars, on the runs with N ≥ 50."""
    out = []
    for r in runs:
        if r["spindles"] >= 50:
            for key, bar in BARS.items():
                value = r[key]
                out.append((f"N={r['spindles']}: {key} {value} <= {bar}", value is not None and value <= bar))
    return out
