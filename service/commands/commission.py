"""``chtc commission zero`` and ``chtc commission growth``: commissioning steps.

``chtc commission growth TEMPERATURES CANLOG DISPLACEMENTS``: fit the growth's mechanics (mount restraint, α
factors) to a measured thermal test (docs/commissioning.md, "Commission the growth";
``service.shell.commissioning``): the service's own core runs over the temperature CSV and the CAN log, as
``chtc identify`` does, and the displacement CSV (UTC time, ``axial_um``, optionally ``radial_um``) is fitted.
Prints the residuals, the parameters with their prior and posterior, and the verdict; ``--json FILE`` writes
the report. Exit status 0 when the model explains the test, 1 when it does not, 2 for unusable input. With
``--url`` the files are sent to the running service instead (``POST /api/v1/compensation/mechanics`` with the
write token), which fits them with its own core, stores the calibration and uses it at once (only when the
model explains the test, or ``--force``).

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
from service.contracts.mechanics import EXAMPLE_NOTE

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
    g = sub.add_parser(
        "growth",
        help="fit the growth's mechanics to a measured thermal test (temperatures, CAN log, displacements)",
    )
    g.add_argument("temperatures", type=Path, help="temperature CSV (chtc record / drivers.logs format)")
    g.add_argument("canlog", type=Path, help="CAN log (.blf/.asc/.log/.csv/.trc/.mf4)")
    g.add_argument("displacements", type=Path, help="displacement CSV: time (UTC), axial_um[, radial_um]")
    g.add_argument("--config", type=Path, default=None, help="settings TOML (default: built-in defaults)")
    g.add_argument("--json", dest="json_out", default=None, help="write the report as JSON here (- stdout)")
    g.add_argument("--max-rms-um", type=float, default=1.0, help="the residual RMS the model may leave, µm")
    g.add_argument("--max-abs-um", type=float, default=3.0, help="the largest residual it may leave, µm")
    g.add_argument(
        "--url",
        default=None,
        help="send the test to this running service, which fits, stores and uses it (default: fit here only)",
    )
    g.add_argument("--token", default=None, help="with --url: the write token (default: api.token)")
    g.add_argument("--set-by", default=None, help="who ran the test (default: the OS user)")
    g.add_argument("--force", action="store_true", help="with --url: store even if the model fails the test")
    g.add_argument("--timeout", type=float, default=600.0, help="with --url: seconds to wait for the service")


class RefusedError(CommandError):
    """The service answered with an error ``status`` (401, 403, 409, 422, ...)."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


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
    body: dict[str, Any] = {"source": "cli", "set_by": set_by}
    if temperature_c is not None:
        body["temperature_c"] = temperature_c
    try:
        return _post(url, "/api/v1/compensation/reference", body, token, "the zero", timeout_s, transport)
    except RefusedError as err:  # the API's field is this command's option (issue 41)
        raise RefusedError(str(err).replace("temperature_c", "--temperature"), err.status) from err


def _post(
    url: str, path: str, body: dict[str, Any], token: str, what: str, timeout_s: float, transport: Any
) -> dict[str, Any]:
    """POST ``body`` with the write ``token`` to ``url`` + ``path``; the JSON answer, or ``CommandError``
    naming ``what`` was refused and the service's message (or why it could not be reached)."""
    import httpx

    target = url.rstrip("/") + path
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
        raise RefusedError(f"the service refused {what} ({resp.status_code}): {message}", resp.status_code)
    out: dict[str, Any] = resp.json()
    return out


def send_growth(
    url: str,
    token: str,
    *,
    temperatures: Path,
    canlog: Path,
    displacements: Path,
    set_by: str,
    force: bool = False,
    timeout_s: float = 600.0,
    transport: Any = None,
) -> dict[str, Any]:
    """POST the test's files to ``url``'s ``/api/v1/compensation/mechanics``; the service's answer (JSON);
    ``CommandError`` with the service's message when it refuses (401/403/409/422) or cannot be reached."""
    import base64

    try:
        body: dict[str, Any] = {
            "temperatures_csv": temperatures.read_text(encoding="utf-8"),
            "can_log_base64": base64.b64encode(canlog.read_bytes()).decode("ascii"),
            "can_log_format": canlog.suffix.lower().lstrip("."),
            "displacements_csv": displacements.read_text(encoding="utf-8-sig"),
            "set_by": set_by,
            "source": "cli",
            "force": force,
        }
    except (OSError, UnicodeDecodeError) as err:
        raise CommandError(f"cannot read the test's files: {err}") from err
    path = "/api/v1/compensation/mechanics"
    return _post(url, path, body, token, "the commissioning", timeout_s, transport)


def _token(args: argparse.Namespace, settings: Any) -> str:
    token = args.token or (settings.api.token.get_secret_value() if settings.api.token is not None else None)
    if not token:
        raise CommandError("--token: a write token is needed (or api.token in the settings, CHTC_API__TOKEN)")
    return str(token)


def _check_not_displacements(temperatures: Path) -> None:
    """``CommandError`` when the file given as TEMPERATURES is the displacement CSV (files swapped)."""
    from service.shell.commissioning import AXIAL, ORDER

    try:
        with temperatures.open(encoding="utf-8-sig", errors="replace") as f:
            head = [next(f, "") for _ in range(20)]
    except OSError:
        return  # a missing file is the reader's to name
    header = next((line for line in head if line.strip() and not line.lstrip().startswith("#")), "")
    if AXIAL in header.lower():
        what = f"argument TEMPERATURES: {temperatures} is the displacement CSV ({AXIAL})"
        raise CommandError(f"{what}: {ORDER}")


def _growth_at(args: argparse.Namespace, settings: Any, set_by: str) -> int:
    """``--url``: the service fits and stores; its report printed as the offline fit's table (the JSON with
    ``--json``); a test the model does not explain is refused (409) with exit status 1, as offline."""
    from service.shell.commissioning import format_report_dict

    try:
        out = send_growth(
            args.url,
            _token(args, settings),
            temperatures=args.temperatures,
            canlog=args.canlog,
            displacements=args.displacements,
            set_by=set_by,
            force=args.force,
            timeout_s=args.timeout,
        )
    except RefusedError as err:
        if err.status != 409:
            raise
        print(f"chtc commission growth: {err}", file=sys.stderr)
        return 1
    for line in format_report_dict(out["report"]):
        print(line)
    if args.json_out is not None:
        text = json.dumps(out, indent=2)
        if args.json_out == "-":
            print(text)
        else:
            Path(args.json_out).write_text(text + "\n", encoding="utf-8")
    print(f"mechanics stored and in use: {out['report']['verdict']}", file=sys.stderr)
    return 0


def growth(args: argparse.Namespace) -> int:
    """``chtc commission growth`` (module docstring)."""
    from service.commands._common import check_log_arguments
    from service.host.runtime import core_config, os_user
    from service.settings import load_settings
    from service.shell.commissioning import FitLimits, commission_growth, format_report

    settings = load_settings(args.config)
    _check_not_displacements(args.temperatures)
    check_log_arguments(args.temperatures, args.canlog)
    set_by = args.set_by or os_user()
    if args.url is not None:
        return _growth_at(args, settings, set_by)
    from service.modelload import ModelRef, load_model
    from service.shell.commissioning import read_displacement_csv

    read_displacement_csv(args.displacements)  # a bad file is reported before the model loads
    model = load_model(ModelRef.from_settings(settings))
    rep = commission_growth(
        model,
        core_config(settings),
        args.temperatures,
        args.canlog,
        args.displacements,
        set_by=set_by,
        source="cli",
        limits=FitLimits(max_rms_um=args.max_rms_um, max_abs_um=args.max_abs_um),
    )
    for line in format_report(rep):
        print(line)
    if "example" in rep.calibration.sources:
        print(f"WARNING: {EXAMPLE_NOTE}; a running service refuses it outside the demo", file=sys.stderr)
    if args.json_out is not None:
        text = json.dumps(rep.as_dict(), indent=2)
        if args.json_out == "-":
            print(text)
        else:
            Path(args.json_out).write_text(text + "\n", encoding="utf-8")
    if rep.explained:
        print(
            "store it in the running service: the same command with --url http://HOST:PORT/ "
            "(and --token or api.token)",
            file=sys.stderr,
        )
    return 0 if rep.explained else 1


def main(args: argparse.Namespace) -> int:
    if args.action == "growth":
        return growth(args)
    from service.host.runtime import os_user
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
