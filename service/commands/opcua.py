"""``chtc opcua``: the OPC UA outlet's tools (docs/integration.md, "OPC UA").

- ``chtc opcua nodeset [--out FILE]``: the NodeSet2 XML of our namespace (the ``SpindleThermalModelType`` and
  the spindle's instance with its string NodeIds, named ``[opcua] spindle`` or ``spindle.id``; with
  ``[[spindles]]`` one instance per spindle, named by its id), valid against the OPC Foundation's schemas, to
  import into TIA Portal (OPC UA client interface) or TwinCAT (TF6100 ``UA_*`` blocks, the Target Browser).
  Built offline: no service, no network.
- ``chtc opcua user NAME``: a PBKDF2-SHA256 hash of a password read from the terminal (or
  ``--password-stdin``) for ``[opcua] users`` or the users file (``NAME = "pbkdf2_sha256$..."``).
"""

from __future__ import annotations

import argparse
import asyncio
import getpass
import sys
import tempfile
from pathlib import Path

from service.commands._common import CommandError

__all__ = ["add_arguments", "main"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    n = sub.add_parser("nodeset", help="write the NodeSet2 XML (for TIA Portal / TwinCAT)")
    n.add_argument("--out", type=Path, default=None, help="file to write (default: stdout)")
    n.add_argument(
        "--config",
        type=Path,
        default=None,
        help="settings TOML ([spindle] id or [opcua] spindle, namespace_uri)",
    )
    u = sub.add_parser("user", help="print a password hash for [opcua] users")
    u.add_argument("name", help="the user name")
    u.add_argument("--password-stdin", action="store_true", help="read the password from stdin")


def main(args: argparse.Namespace) -> int:
    if args.action == "user":
        return _user(args)
    from service.serve.opcua.nodes import variables
    from service.serve.opcua.server import export_nodeset
    from service.settings import load_settings

    settings = load_settings(args.config)
    cfg = settings.opcua.for_spindle(settings.spindle.id)
    spindles: list[str] = []
    if settings.spindles:  # a cell: one object per spindle, named by its id
        if settings.opcua.spindle is not None:
            raise CommandError(
                "opcua.spindle names the object of one spindle; with [[spindles]] each object is named by "
                "its spindles[i].id (unset opcua.spindle)"
            )
        spindles = [s.spindle.id for s in settings.per_spindle()]
    if args.out is not None:
        count = asyncio.run(export_nodeset(cfg, variables(), args.out, spindles=spindles))
        objects = len(spindles) or 1
        print(
            f"wrote {args.out}: {count} variables ({objects} spindle object(s) and their type) in "
            f"{cfg.namespace_uri}",
            file=sys.stderr,
        )
        return 0
    with tempfile.TemporaryDirectory(prefix="chtc-nodeset-") as tmp:
        path = Path(tmp) / "nodeset.xml"
        asyncio.run(export_nodeset(cfg, variables(), path, spindles=spindles))
        sys.stdout.write(path.read_text(encoding="utf-8"))
    return 0


def _user(args: argparse.Namespace) -> int:
    from service.serve.opcua.security import hash_password

    if args.name.lower() == "admin":
        raise CommandError("name: 'admin' is refused (asyncua treats it as an administrator)")
    if args.password_stdin:
        password = sys.stdin.readline().rstrip("\n")
    else:
        password = getpass.getpass(f"password for {args.name}: ")
        if password != getpass.getpass("again: "):
            raise CommandError("the two passwords differ")
    if len(password) < 12:
        raise CommandError("password: at least 12 characters")
    print(f'{args.name} = "{hash_password(password)}"')
    return 0
