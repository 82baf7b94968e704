"""What the ``chtc`` commands share: one-line user errors, validated overrides and a listen-port check.

Error tree (all reported by the commands as one line ``chtc <command>: <message>``, exit status 2)::

    ValueError
    └── CommandError        bad command-line value, address in use, unusable input (names the option)

``service.settings.SettingsError``, ``drivers.errors.ConfigError``, ``drivers.logs.LogFormatError`` and
``service.contracts.errors.CommissioningError`` are reported the same way by the commands
(``USER_ERRORS``).
"""

from __future__ import annotations

import argparse
import socket
from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import ServiceError

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = [
    "CommandError",
    "DefaultsHelpFormatter",
    "check_database_url",
    "check_listen",
    "check_listens",
    "check_log_arguments",
    "override",
    "port_number",
    "user_errors",
]


class CommandError(ServiceError, ValueError):
    """A user error in a command's options or inputs; the message names the option or file."""


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to every option's help unless the help already states its default.

    Options whose default is ``None`` or a flag's ``False`` get nothing appended: their help says what
    happens without them (checked by tests/service/test_cli_usability.py).
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            "default" in text.lower()
            or not action.option_strings
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or action.nargs == 0
        ):
            return text
        return f"{text} (default: %(default)s)" if text else "(default: %(default)s)"


def port_number(text: str) -> int:
    """An argparse ``type``: a TCP port 0-65535 (0: a free one where the option allows it)."""
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not a TCP port number (0-65535)") from err
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{value} is not a TCP port number (0-65535)")
    return value


def positive_float(text: str) -> float:
    """An argparse ``type``: a number > 0."""
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from err
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{value:g} must be > 0")
    return value


def override(settings: Settings, section: str, **values: object) -> Settings:
    """``settings`` with ``section.key = value`` replaced and validated like the config file would be.

    ``model_copy(update=...)`` does not validate, so a garbage ``--database-url`` or port used to pass and
    fail deep inside (a traceback). Raises ``CommandError`` naming ``section.key``.
    """
    from pydantic import ValidationError

    current = getattr(settings, section)
    try:
        checked = type(current).model_validate({**current.model_dump(), **values})
    except ValidationError as err:
        problems = "; ".join(
            f"{section}.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}"
            for e in err.errors(include_url=False)
        )
        raise CommandError(problems) from err
    from service.settings import check_across_sections

    out = settings.model_copy(update={section: checked})
    try:
        check_across_sections(out)
    except ValueError as err:
        raise CommandError(str(err)) from err
    return out


def check_listens(settings: Settings) -> None:
    """``check_listen`` on every port this instance serves: the REST API, and the OPC UA server when enabled
    (a busy OPC UA port was three tracebacks after the model had loaded: issue 41)."""
    check_listen(settings.api.host, settings.api.port)
    ua = settings.opcua
    if ua.enabled:
        try:
            check_listen(ua.host, ua.port)
        except CommandError as err:
            raise CommandError(f"opcua.port: {err} (the OPC UA server's port)") from err


def check_listen(host: str, port: int) -> None:
    """Raise ``CommandError`` if ``host:port`` cannot be listened on (busy, or not a local address).

    Checked before the model loads (about 10 s) so a busy port is reported at once. The socket is bound with
    SO_REUSEADDR like uvicorn's, so a port in TIME_WAIT is not reported busy. Port 0 is always fine.
    """
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as err:
        raise CommandError(f"cannot listen on {host}:{port}: {err}") from err
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(address)
            s.listen(1)
        except OSError as err:
            raise CommandError(f"cannot listen on {host}:{port}: {err.strerror or err}") from err


def check_database_url(url: str, option: str) -> None:
    """Raise ``CommandError`` naming ``option`` unless the store can use ``url``: a supported backend and
    driver (``service.store.engine.SUPPORTED_DATABASES``) that is installed, and for SQLite a directory that
    exists or can be created.

    Checked before the model loads: ``mysql://…`` used to load the model for 46 s and then end in a
    traceback (``No module named 'MySQLdb'``).
    """
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    from service.store.dburl import normalize_database_url
    from service.store.engine import SUPPORTED_DATABASES

    examples = "sqlite:///PATH or postgresql+psycopg://USER:PASSWORD@HOST:PORT/DB"
    try:
        parsed = make_url(normalize_database_url(url))
    except ArgumentError as err:
        raise CommandError(f"{option}: not a database URL: {url!r} (use {examples})") from err
    backend, driver = parsed.get_backend_name(), parsed.get_driver_name()
    if backend not in SUPPORTED_DATABASES:
        raise CommandError(f"{option}: database {backend!r} is not supported (use {examples})")
    if driver not in SUPPORTED_DATABASES[backend]:
        wanted = " or ".join(f"{backend}+{d}://" for d in SUPPORTED_DATABASES[backend])
        raise CommandError(f"{option}: driver {driver!r} is not supported for {backend} (use {wanted})")
    try:
        parsed.get_dialect().import_dbapi()
    except ImportError as err:
        raise CommandError(f"{option}: the {backend} driver {driver!r} is not installed ({err})") from err
    database = parsed.database or ""
    if backend == "sqlite" and database not in ("", ":memory:") and not database.startswith("file:"):
        parent = Path(database).expanduser().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise CommandError(
                f"{option}: cannot create the SQLite directory {parent}: {err.strerror or err}"
            ) from err


def check_log_arguments(csv: Path, can: Path | None) -> None:
    """Raise ``CommandError`` naming the argument when the logs are given in the wrong order or role.

    ``chtc identify can.blf temps.csv`` used to end in ``'utf-8' codec can't decode byte 0x90``: the
    temperature CSV comes first, the CAN log second. A missing file is left to the readers (they name it).
    """
    from drivers.logs import CAN_LOG_SUFFIXES, csv_header

    order = "give the temperature CSV first, then the CAN log"
    suffix = csv.suffix.lower()
    if suffix in CAN_LOG_SUFFIXES and suffix != ".csv":
        raise CommandError(f"argument CSV: {csv} is not a temperature CSV but a CAN log ({suffix}); {order}")
    head = _first_bytes(csv)
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as err:
        if err.start < len(head) - 4:  # not a multi-byte character cut at the end of the sample
            raise CommandError(
                f"argument CSV: {csv} is not a temperature CSV (binary content, not UTF-8 text); {order}"
            ) from err
    if can is not None and can.suffix.lower() == ".csv":
        first = _first_bytes(can).split(b"\n", 1)[0].decode("utf-8", "replace").strip()
        if first.split(",")[:2] == csv_header()[:2]:
            raise CommandError(
                f"argument CAN: {can} is not a CAN log but a temperature CSV (its header starts "
                f"{','.join(csv_header()[:2])}); {order}"
            )


def _first_bytes(path: Path, n: int = 4096) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(n)
    except OSError:
        return b""


def user_errors() -> tuple[type[Exception], ...]:
    """The exception types a command reports as one line (imported lazily: ``chtc --help`` stays fast)."""
    from drivers.errors import ConfigError
    from drivers.logs import LogFormatError
    from service.contracts.errors import CommissioningError
    from service.serve.errors import OutletError
    from service.settings import SettingsError

    return (CommandError, SettingsError, ConfigError, LogFormatError, CommissioningError, OutletError)
