"""``python -m benchmarks NAME [options]``: the benchmarks' command line (what ``chtc bench`` was).

Each benchmark lives in ``benchmarks.<name>``, imported only when it runs (``--help`` stays instant, and a
broken benchmark cannot break the others), and exposes ``add_arguments(parser)`` and ``main(args) -> int``.
A user error (bad option, setting, file) is one line ``benchmarks NAME: message``, exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from service.commands._common import DefaultsHelpFormatter, user_errors

PROG = "python -m benchmarks"

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
    "robustness": "the product vs MLR, ridge, LASSO and ARX peers where regressions fail: ambient ramps and "
    "cycles, other duty spectra, airflow, sensor faults, restarts, a changed machine (issue 40)",
}


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The parser; only the benchmark named in ``argv[0]`` is imported and given its options."""
    parser = argparse.ArgumentParser(
        prog=PROG, description="spindle-chtc benchmarks: print figures (not tests)."
    )
    sub = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    wanted = argv[0] if argv else None
    for name, text in BENCHMARKS.items():
        p = sub.add_parser(name, help=text, description=text, formatter_class=DefaultsHelpFormatter)
        if name == wanted:
            module = importlib.import_module(f"benchmarks.{name}")
            module.add_arguments(p)
            p.set_defaults(_module=module)
    return parser


def _limit_blas_threads() -> None:
    """One BLAS thread per process, as ``chtc`` does (service.cli): must happen before numpy is imported."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def main(argv: Sequence[str] | None = None) -> int:
    _limit_blas_threads()
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = build_parser(args_list).parse_args(args_list)
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a user error (bad config, option, file) is one line, not a traceback
        if not isinstance(err, user_errors()):
            raise
        print(f"benchmarks {args.benchmark}: {err}", file=sys.stderr)
        return 2
