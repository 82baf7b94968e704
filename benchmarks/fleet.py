"""``python -m benchmarks fleet``: spindles hosted as the product hosts them (``--spindles``), and how many
instances one PostgreSQL server holds on the write side (``--writers``).

``--spindles 10,50`` (the default): ``benchmarks.fleet_host``: N spindles in one ``chtc run`` with
``[[spindles]]``, their devices in another process at real rates, one PostgreSQL; write p99, memory per added
spindle, CPU per spindle, connections, bytes per spindle-day; plus the retention pass at 500 spindle-days
(``benchmarks.storage.retention_at``). ``--writers-only`` skips it and runs only the write-capacity part
below.

The write-capacity part:

Each instance writes about one sample row per ``database.sample_store_period_s`` (10 s), plus rare condition,
identification and device-event rows, each batch in its own transaction (``service.store.writer``). This bench
starts K writer threads, each standing for one instance with its own database on the server (the layout
deploy/OPERATIONS.md recommends: one database per spindle), and commits single-sample transactions through
the real repository code (``service.store.repository.write_records``) as fast as it can for ``--seconds``.
Figures per K: committed transactions/s, commit latency median and p99, and the number of instances that
rate carries at one sample per 10 s. The same loop against a local SQLite file (one writer) is the peer.
The bench client shares the machine with the server, so the figures are lower bounds for a dedicated server.

The databases ``chtc_bench_fleet_<i>`` are created (dropped first) and dropped at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from benchmarks.fleet_host import DEFAULT_PG
from benchmarks.targets import format_verdicts

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine
    from sqlalchemy.orm import Session, sessionmaker

    from service.contracts.records import SampleData

SAMPLE_PERIOD_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m benchmarks fleet``."""
    parser.add_argument("--pg-url", default=DEFAULT_PG, help="a PostgreSQL URL with CREATE DATABASE rights")
    parser.add_argument("--writers", default="1,4,16", help="comma-separated K (concurrent instances)")
    parser.add_argument("--seconds", type=float, default=5.0, help="measuring time per K, s")
    parser.add_argument("--runs", type=int, default=3, help="repeats per K (medians are reported)")
    parser.add_argument(
        "--spindles",
        default="10,50",
        help="comma-separated N spindles hosted in one process (N = 1 is run first)",
    )
    parser.add_argument("--warmup-s", type=float, default=60.0, help="per N: seconds before the window")
    parser.add_argument("--window-s", type=float, default=120.0, help="per N: the measuring window, s")
    parser.add_argument(
        "--plants", type=int, default=4, help="distinct virtual-plant duty cycles the spindles play"
    )
    parser.add_argument(
        "--retention-runs", type=int, default=3, help="retention passes at 500 spindle-days (median quoted)"
    )
    parser.add_argument(
        "--writers-only", action="store_true", help="only the write-capacity part (no hosting)"
    )
    parser.add_argument(
        "--outlets",
        default="",
        help="comma-separated protocol outlets on for every hosted spindle: opcua, mqtt (the bench starts "
        "its own Mosquitto); none by default",
    )
    parser.add_argument("--json", action="store_true")


def _sample(i: int) -> SampleData:
    from service.contracts.records import SampleData

    return SampleData(
        t=datetime.now(UTC),
        temps_c=[20.0 + 0.01 * ((i + c) % 100) for c in range(32)],
        ambient_c=22.0,
        speed_rpm=3000.0,
        torque_nm=5.0,
        quality=["ok"] * 32,
    )


def _writer_loop(factory: sessionmaker[Session], stop_at: float, latencies: list[float]) -> None:
    from service.store.repository import write_records

    i = 0
    while (start := time.perf_counter()) < stop_at:
        with factory.begin() as session:
            write_records(session, [_sample(i)])
        latencies.append(time.perf_counter() - start)
        i += 1


def measure(factories: list[sessionmaker[Session]], seconds: float) -> dict[str, float]:
    """K threads (one per session factory) committing single-sample transactions for ``seconds``."""
    per_thread: list[list[float]] = [[] for _ in factories]
    stop_at = time.perf_counter() + seconds
    threads = [
        threading.Thread(target=_writer_loop, args=(f, stop_at, lat))
        for f, lat in zip(factories, per_thread, strict=True)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lat = sorted(x for lst in per_thread for x in lst)
    tps = len(lat) / seconds
    return {
        "tx_per_s": tps,
        "commit_ms_p50": 1e3 * lat[len(lat) // 2],
        "commit_ms_p99": 1e3 * lat[min(len(lat) - 1, int(0.99 * len(lat)))],
        "instances_at_10s": tps * SAMPLE_PERIOD_S,
    }


def _medians(runs: list[dict[str, float]]) -> dict[str, float]:
    return {k: round(statistics.median(r[k] for r in runs), 3) for k in runs[0]}


def _pg_databases(pg_url: str, k: int) -> tuple[list[sessionmaker[Session]], tuple[Engine, list[Engine]]]:
    import sqlalchemy as sa
    from sqlalchemy.engine import make_url

    from service.store.engine import create_db_engine, make_session_factory
    from service.store.migrate import upgrade

    admin = sa.create_engine(pg_url, isolation_level="AUTOCOMMIT")
    engines = []
    with admin.connect() as conn:
        for i in range(k):
            name = f"chtc_bench_fleet_{i}"
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
            conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
            url = make_url(pg_url).set(database=name).render_as_string(hide_password=False)
            engine = create_db_engine(url)
            upgrade(engine)
            engines.append(engine)
    return [make_session_factory(e) for e in engines], (admin, engines)


def _drop_pg(handles: tuple[Engine, list[Engine]], k: int) -> None:
    import sqlalchemy as sa

    admin, engines = handles
    for e in engines:
        e.dispose()
    with admin.connect() as conn:
        for i in range(k):
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "chtc_bench_fleet_{i}" WITH (FORCE)'))
    admin.dispose()


def _sqlite_run(seconds: float, runs: int) -> dict[str, float]:
    from service.store.engine import create_db_engine, make_session_factory
    from service.store.migrate import upgrade

    with tempfile.TemporaryDirectory() as tmp:
        engine = create_db_engine(f"sqlite:///{Path(tmp) / 'bench.db'}")
        upgrade(engine)
        factory = make_session_factory(engine)
        result = _medians([measure([factory], seconds) for _ in range(runs)])
        engine.dispose()
    return result


def main(args: argparse.Namespace) -> int:
    """Run ``python -m benchmarks fleet``."""
    if args.writers_only:
        return writers_main(args)
    from benchmarks.fleet_host import parse_outlets

    try:
        outlets = parse_outlets(args.outlets)
    except ValueError as err:
        return _refuse(str(err))
    if (refusal := _host_refusal(outlets)) is not None:
        return _refuse(f"--outlets {args.outlets}: the host refuses it: {refusal}")
    broker = None
    if "mqtt" in outlets:
        from benchmarks.opcua import Broker

        broker = Broker()
    try:
        return _hosted(args, outlets, mqtt_port=0 if broker is None else broker.port)
    finally:
        if broker is not None:
            broker.stop()


def _refuse(message: str) -> int:
    import sys

    print(f"benchmarks fleet: {message}", file=sys.stderr)
    return 2


def _host_refusal(outlets: frozenset[str]) -> str | None:
    """The host's own refusal of these outlets with ``[[spindles]]`` (e.g. ``[mqtt]`` before MQTT is hosted),
    checked on a two-spindle configuration before anything starts; None when it takes them."""
    from benchmarks.fleet_host import host_toml, outlets_for, refused_by_host

    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "check.toml"
        o = outlets_for(outlets, mqtt_port=1883, state_dir=tmp)
        config.write_text(host_toml("sqlite://", 8000, [5020, 5021], [8001, 8002], o), encoding="utf-8")
        return refused_by_host(config)


def _hosted(args: argparse.Namespace, outlets: frozenset[str], *, mqtt_port: int) -> int:
    from benchmarks.fleet_host import measure_fleet, verdicts
    from benchmarks.storage import retention_at

    ns = sorted({int(x) for x in args.spindles.split(",") if x.strip()})
    started = datetime.now(UTC).isoformat(timespec="seconds")
    report: dict[str, Any] = measure_fleet(
        ns,
        pg_url=args.pg_url,
        warmup_s=args.warmup_s,
        window_s=args.window_s,
        plants=args.plants,
        outlets=outlets,
        mqtt_port=mqtt_port,
    )
    passes = sorted(float(retention_at(args.pg_url, 50, 10)["pass_s"]) for _ in range(args.retention_runs))
    report["retention_pass_s_500_spindle_days"] = round(statistics.median(passes), 3)
    report["retention_passes_s"] = [round(x, 3) for x in passes]
    report["cpu_count"] = os.cpu_count()
    report["utc"] = started  # when the bench started; utc_end when it reported
    report["utc_end"] = datetime.now(UTC).isoformat(timespec="seconds")
    checks = verdicts(report["runs"])
    report["verdicts"] = [{"bar": text, "met": ok} for text, ok in checks]
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    head = (
        f"{'N':>5}{'running':>9}{'write p99 ms':>14}{'MiB/added':>11}{'CPU %/sp.':>11}{'B/sp.-day':>12}"
        f"{'conns':>7}{'load':>7}"
    )
    print(head)
    for r in [report["baseline"], *report["runs"]]:
        print(
            f"{r['spindles']:>5}{r['running']:>9}{r['write_p99_ms'] or float('nan'):>14.2f}"
            f"{r.get('mib_per_added_spindle', float('nan')):>11.2f}{r['cpu_pct_per_spindle']:>11.3f}"
            f"{r['bytes_per_spindle_day']:>12d}{r['connections']:>7d}{r['load_average_1min']:>7.2f}"
        )
    print(f"outlets: {', '.join(k for k, on in report['outlets'].items() if on) or 'none'} (beside REST)")
    print(f"retention pass at 500 spindle-days: {report['retention_pass_s_500_spindle_days']} s")
    for text, ok in checks:
        print(f"  {'met   ' if ok else 'MISSED'} {text}")
    return 0


def writers_main(args: argparse.Namespace) -> int:
    """The write-capacity part (``--writers-only``)."""
    ks = sorted({int(x) for x in args.writers.split(",") if x.strip()})
    factories, handles = _pg_databases(args.pg_url, max(ks))
    report: dict[str, Any] = {"sample_period_s": SAMPLE_PERIOD_S, "seconds": args.seconds, "runs": args.runs}
    try:
        report["postgresql"] = {
            str(k): _medians([measure(factories[:k], args.seconds) for _ in range(args.runs)]) for k in ks
        }
    finally:
        _drop_pg(handles, max(ks))
    report["sqlite_1_writer"] = _sqlite_run(args.seconds, args.runs)
    report["load_average_1min"] = round(os.getloadavg()[0], 2)
    report["cpu_count"] = os.cpu_count()
    print(json.dumps(report, indent=2) if args.json else _table(report))
    return 0


def _table(report: dict[str, Any]) -> str:
    head = f"{'backend':<22}{'tx/s':>10}{'p50 ms':>10}{'p99 ms':>10}{'instances @10 s':>18}"
    rows = [head]
    items = [(f"postgresql K={k}", r) for k, r in report["postgresql"].items()]
    items.append(("sqlite K=1", report["sqlite_1_writer"]))
    for name, r in items:
        rows.append(
            f"{name:<22}{r['tx_per_s']:>10.0f}{r['commit_ms_p50']:>10.2f}{r['commit_ms_p99']:>10.2f}"
            f"{r['instances_at_10s']:>18.0f}"
        )
    rows.append(
        f"(medians of {report['runs']} runs of {report['seconds']} s; load {report['load_average_1min']})"
    )
    rows.append(format_verdicts([]) + " (a capacity figure: instances one server carries)")
    return "\n".join(rows)
