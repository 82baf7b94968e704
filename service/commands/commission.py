"""``chtc commission zero``: store the compensation zero in a running service, through its API.

The zero is a commissioning fact (docs/commissioning.md, "Zero the compensation"): with the spindle at rest in
equilibrium, the controller's thermal compensation is zeroed (the tool measured), and the service is told the
same instant with ``POST /api/v1/compensation/reference``. This command is that request: the running service
takes the reference from its live field (or ``--temperature``), stores it in its database and uses it at once;
every later start restores it. It goes through the API rather than into the database, because the service
reads its reference at start only: a row written behind its back would take effect at the next restart.

The URL and token come from ``--url``/``--token``, else from the settings (``--config``, ``CHTC_API__TOKEN``):
``http://<api.host>:<api.port>/`` and ``api.token``. ``set_by`` is ``--set-by`` or the OS user.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from service.commands._common import CommandError

__all__ = ["add_arguments", "main", "zero"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    z = sub.add_parser("zero", help="store the compensation zero now (spindle at rest, controller zeroed)")
    z.add_argument("--url", default=None, help="the service's URL (default: http://<api.host>:<api.port>/)")
    z.add_argument("--token", default=None, help="the write token (default: api.token from the settings)")
    z.add_argument("--config", type=Path, default=None, help="settings TOML (for the URL and the token)")
    z.add_argument(
        "--temperature",
        type=float,
        default=None,
        help="the uniform temperature of the zero, °C (default: the service takes it from its live field)",
    )
    z.add_argument("--set-by", default=None, help="who zeroed the controller (default: the OS user)")
    z.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the service")


def zero(
    url: str,
    token: str,
    *,
    temperature_c: float | None,
    set_by: str,
    timeout_s: float = 30.0,
    transport: Any = None,
) -> dict[str, Any]:
    """POST the zero to ``url`` (the service's base URL) and return the stored reference (JSON object);
    ``CommandError`` with the service's message when it refuses (401/403/409/422) or cannot be reached."""
    import httpx

    body: dict[str, Any] = {"source": "cli", "set_by": set_by}
    if temperature_c is not None:
        body["temperature_c"] = temperature_c
    target = url.rstrip("/") + "/api/v1/compensation/reference"
    try:
        with httpx.Client(timeout=timeout_s, transport=transport) as client:
            resp = client.post(target, json=body, headers={"Authorization": f"Bearer {token}"})
    except httpx.HTTPError as err:
        raise CommandError(f"--url: cannot reach {target}: {err}") from err
    if resp.status_code != 200:
        try:
            message = resp.json().get("error", {}).get("message", resp.text)
        except ValueError:
            message = resp.text
        raise CommandError(f"the service refused the zero ({resp.status_code}): {message}")
    out: dict[str, Any] = resp.json()
    return out


def main(args: argparse.Namespace) -> int:
    from service.engine.runtime import os_user
    from service.settings import load_settings

    settings = load_settings(args.config)
    url = args.url or f"http://{settings.api.host}:{settings.api.port}/"
    token = args.token or (settings.api.token.get_secret_value() if settings.api.token is not None else None)
    if not token:
        raise CommandError("--token: a write token is needed (or api.token in the settings, CHTC_API__TOKEN)")
    ref = zero(
        url, token, temperature_c=args.temperature, set_by=args.set_by or os_user(), timeout_s=args.timeout
    )
    print(json.dumps(ref, indent=2))
    print(
        f"compensation zero stored: {ref['temperature_c']} °C ± {ref['sd_c']} at {ref['at']} "
        f"({ref['source']}, by {ref['set_by']})",
        file=sys.stderr,
    )
    return 0
