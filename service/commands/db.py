"""``chtc db upgrade|retention|merge``: database chores on the settings' database (``[database] url``).

- ``chtc db upgrade``: migrate to the newest revision (rows stored before ``0007`` get ``[spindle] id``);
- ``chtc db retention``: one retention pass now (``service.store.retention``; the service runs one a day):
  raw samples older than ``database.raw_days`` dropped (PostgreSQL: whole daily partitions), minute means
  older than ``database.minute_days`` deleted, the next days' partitions made; prints what it did;
- ``chtc db merge SRC --spindle ID``: copy a one-spindle database (today's deployment) into this shared one
  under spindle ``ID`` (``service.store.merge``; SRC is migrated in place first: back it up).

``--url`` overrides the settings' URL; ``--config`` is the settings TOML.
"""

from __future__ import annotations

import argparse
import re
from datetime import UTC, datetime
from pathlib import Path

from service.commands._common import CommandError

__all__ = ["add_arguments", "main"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, text in (
        ("upgrade", "migrate the database to the newest revision (old rows get [spindle] id)"),
        ("retention", "run one retention pass now: drop old raw samples and minute means"),
        ("merge", "copy a one-spindle database into this one, under a spindle id"),
    ):
        p = sub.add_parser(name, help=text, description=text)
        p.add_argument("--config", type=Path, default=None, help="settings TOML (default: built-in defaults)")
        p.add_argument("--url", default=None, help="database URL (default: [database] url)")
        if name == "retention":
            p.add_argument("--raw-days", type=int, default=None, help="default: database.raw_days")
            p.add_argument("--minute-days", type=int, default=None, help="default: database.minute_days")
        if name == "merge":
            p.add_argument(
                "source", help="the one-spindle database's URL (sqlite:///path or postgresql+psycopg://…)"
            )
            p.add_argument("--spindle", required=True, help="the spindle id its rows get (e.g. cell3-s07)")


def main(args: argparse.Namespace) -> int:
    from service.settings import SPINDLE_ID_PATTERN, SettingsError, load_settings

    try:
        settings = load_settings(args.config)
    except SettingsError as err:
        raise CommandError(str(err)) from err
    url = args.url or settings.database.url
    if args.action == "upgrade":
        from service.store.migrate import current_revision, upgrade

        upgrade(url, spindle_id=settings.spindle.id)
        print(f"database at revision {current_revision(url)}")
        return 0
    if args.action == "retention":
        return _retention(url, args, settings.database.raw_days, settings.database.minute_days)
    if not re.match(SPINDLE_ID_PATTERN, args.spindle):
        raise CommandError(f"--spindle {args.spindle!r}: not a spindle id ({SPINDLE_ID_PATTERN})")
    from service.store.merge import MergeError, merge

    try:
        report = merge(args.source, url, spindle_id=args.spindle)
    except MergeError as err:
        raise CommandError(str(err)) from err
    total = sum(report.rows.values())
    print(f"merged {total} rows of spindle {report.spindle_id} in {report.seconds:.1f} s:")
    for table, n in report.rows.items():
        print(f"  {table:<26} {n:>10}")
    return 0


def _retention(url: str, args: argparse.Namespace, raw_days: int, minute_days: int) -> int:
    from service.store.engine import create_db_engine
    from service.store.retention import retention_pass

    engine = create_db_engine(url)
    try:
        r = retention_pass(
            engine,
            now=datetime.now(UTC),
            raw_days=raw_days if args.raw_days is None else args.raw_days,
            minute_days=minute_days if args.minute_days is None else args.minute_days,
        )
    finally:
        engine.dispose()
    print(
        f"retention: raw samples before {r.raw_cutoff or 'never'}, minute means before "
        f"{r.minute_cutoff or 'never'}; {len(r.partitions_dropped)} partitions dropped, "
        f"{r.raw_rows_deleted} raw and {r.minute_rows_deleted} minute rows deleted, {r.minutes_backfilled} "
        f"minutes backfilled, {len(r.partitions_created)} partitions made, {r.seconds:.3f} s; "
        f"{len(r.partitions_compacted)} closed days' indexes compacted, {r.compact_seconds:.3f} s"
    )
    return 0
