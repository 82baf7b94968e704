"""What the ``chtc`` commands share: one-line user errors, validated overrides and a listen-port check.

Error tree (all reported by the commands as one line ``chtc <command>: <message>``, exit status 2)::

    ValueError
    └── CommandError        bad command-line value, address in use, unusable input (names the option)

``service.settings.SettingsError``, ``drivers.errors.ConfigError`` and ``drivers.logs.LogFormatError`` are
reported the same way by the commands (``USER_ERRORS``).
"""

from __future__ import annotations

import argparse
import socket
from typing import TYPE_CHECKING

from service.errors import ServiceError

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = [
    "CommandError",
    "DefaultsHelpFormatter",
    "check_listen",
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


def user_errors() -> tuple[type[Exception], ...]:
    """The exception types a command reports as one line (imported lazily: ``chtc --help`` stays fast)."""
    from drivers.errors import ConfigError
    from drivers.logs import LogFormatError
    from service.settings import SettingsError

    return (CommandError, SettingsError, ConfigError, LogFormatError)
