"""The ``chtc`` command line.

Each sub-command lives in its own module, ``service.commands.<name>`` (``run``, ``demo``, ``simulate``,
``record``, ``replay``, ``identify``, ``prebuild``, ``commission``, ``opcua``, ``db``), imported only when it
runs, so that ``chtc --help`` is instant and a broken optional component cannot break the others. Every such
module exposes ``add_arguments(parser)`` and ``main(args) -> int``.

The benchmarks are not the operator's: they run as ``python -m benchmarks NAME`` from a source tree
(``benchmarks.cli``).
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
        print(f"chtc {args.command}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
