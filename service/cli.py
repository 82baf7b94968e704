"""The ``chtc`` command line.

Each sub-command lives in its own module, imported only when it runs, so that ``chtc --help`` is instant and a
broken optional component cannot break the others:

- ``service.commands.<name>`` for the product commands (``run``, ``demo``, ``simulate``, ``record``,
  ``replay``, ``identify``, ``prebuild``, ``commission``, ``opcua``, ``db``);
- ``service.bench.<name>`` for the benchmarks
  (``chtc bench model|optim|identify|chain|acquisition|api|fleet|truth|restart|growth|duty|compensation|
  commission|opcua|storage``).

Every such module exposes ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from types import ModuleType

from service.commands._common import DefaultsHelpFormatter, user_errors

COMMANDS: dict[str, str] = {
    "run": "run the soft sensor against real devices (Modbus DAQ + CAN), with the API and dashboard",
    "demo": "simulated devices + virtual plant + service + API + dashboard on SQLite; prints the URL",
    "simulate": "serve the simulated Modbus DAQ and CAN node (driven by the virtual plant) or a replay",
    "record": "record live devices into a temperature CSV and a CAN log",
    "replay": "play recorded logs through simulated devices into the unchanged service",
    "identify": "offline, deterministic identification of H1-H7 from recorded log files",
    "prebuild": "build the FE model and the reduced-model cache ahead of time (container images, installs)",
    "commission": "commissioning steps: `zero` stores the compensation zero; `growth` fits the mechanics "
    "to a measured thermal test",
    "opcua": "OPC UA outlet tools: `nodeset` writes the NodeSet2 XML (TIA Portal, TwinCAT); `user` hashes a "
    "password",
    "db": "database chores: `upgrade` migrates, `retention` drops old samples now, `merge` copies a "
    "one-spindle database into a shared one",
}

BENCHMARKS: dict[str, str] = {
    "model": "FE and reduced-model speed and accuracy",
    "optim": "IGWO (paper/normalized), GWO, WOA, GA on the paper's benchmark functions and shifted versions",
    "identify": "identification methods on virtual-plant data at the paper's two conditions",
    "acquisition": "Modbus poll latency, CAN decode rate, ring buffer, reconnect time",
    "api": "GET /chtc latency on chtc demo (real rate, x60; quiet, beside a CPU hog)",
    "chain": "the service's answers over a chain of conditions: H error and CI coverage vs the plant's truth",
    "fleet": "N spindles in one process at real rates, one PostgreSQL: write p99, MiB and CPU per spindle",
    "truth": "hidden random truths (6000-7000 rpm, drift, torque steps, offsets): H error, CI coverage",
    "restart": "restart on a warm spindle (minute 0/30/60/90): H error, CI coverage, time to the first H",
    "growth": "served thermal growth at the nose vs the plant's own: error, CI coverage, forecast, cost",
    "duty": "a machining duty cycle (speed changes every 1-6 min): fresh H, error and coverage vs the truth",
    "compensation": "served /compensation every minute vs random H(speed) truths: usable, error, coverage, "
    "restarts, outages",
    "opcua": "OPC UA: read p99 with 10 clients, subscription latency, REST /chtc p99 with the outlets on/off",
    "storage": "rows and bytes per spindle-day per table (PostgreSQL), 0006, 0007, head vs the 3 MB bar; the "
    "retention pass at many spindle-days",
    "commission": "the product's commissioning vs an MLR peer (correlation-clustered sensors) on the same "
    "thermal test, then on a duty cycle: axial error of each",
}


def _load(package: str, name: str) -> ModuleType:
    return importlib.import_module(f"{package}.{name}")


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="chtc",
        description="spindle-chtc: online soft sensor for spindle convective heat transfer coefficients.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    wanted = argv[0] if argv else None
    for name, text in COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text, formatter_class=DefaultsHelpFormatter)
        if name == wanted:
            module = _load("service.commands", name)
            module.add_arguments(p)
            p.set_defaults(_module=module)
    bench = sub.add_parser("bench", help="benchmarks: print figures (not tests)", description="Benchmarks.")
    bench_sub = bench.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    wanted_bench = argv[1] if wanted == "bench" and len(argv) > 1 else None
    for name, text in BENCHMARKS.items():
        p = bench_sub.add_parser(name, help=text, description=text, formatter_class=DefaultsHelpFormatter)
        if name == wanted_bench:
            module = _load("service.bench", name)
            module.add_arguments(p)
            p.set_defaults(_module=module)
    return parser


def _limit_blas_threads() -> None:
    """One BLAS thread per process: the FE/ROM solves are small, and OpenBLAS' thread pool made them 2-50x
    slower on a loaded 2-core machine (measured; docs/design/model.md). Must happen before numpy is
    imported."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def main(argv: Sequence[str] | None = None) -> int:
    _limit_blas_threads()
    args_list = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(args_list)
    args = parser.parse_args(args_list)
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a user error (bad config, option, file) is one line, not a traceback
        if not isinstance(err, user_errors()):
            raise
        name = args.command if args.command != "bench" else f"bench {args.benchmark}"
        print(f"chtc {name}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
