"""The dashboard's text rules, run in node on the functions of api/static/app.js as shipped (no browser):
what a newcomer met on its screenshots (issue 41 items 3 and 9)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

APP = Path(__file__).resolve().parents[2] / "api" / "static" / "app.js"

pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")


def _source(name: str) -> str:
    """A top-level ``function name(...) {...}`` or ``const name = ...;`` of app.js, as written."""
    text = APP.read_text(encoding="utf-8")
    m = re.search(rf"^(function {name}\(.*?^}}|const {name} = .*?;)$", text, re.S | re.M)
    assert m is not None, name
    return m.group(1)


def _run(names: list[str], expr: str) -> Any:
    script = "\n".join(_source(n) for n in names) + f"\nconsole.log(JSON.stringify({expr}));"
    out = subprocess.run(["node", "-e", script], capture_output=True, text=True, timeout=30, check=True)
    return json.loads(out.stdout)


def test_a_device_judged_on_a_window_is_never_said_to_be_never_ok() -> None:
    """Item 3: the banner said ``EVENT_LOOP DEGRADED … never ok`` on every screenshot under load, though the
    log said ``degraded->ok recovered`` several times: the event loop (and the core) have no last-ok time."""
    names = ["fmtSig", "ageText", "DEVICE_CAUSES", "NO_LAST_OK", "deviceCauses"]
    lagging = "loop_lagging: max lag 900 ms"
    loop = {"name": "event_loop", "status": "degraded", "age_s": None, "message": lagging}
    daq = {"name": "modbus", "status": "down", "age_s": None, "message": "cannot connect"}
    causes = _run(names, f"deviceCauses({{devices: [{json.dumps(loop)}, {json.dumps(daq)}]}})")
    assert causes[0]["detail"] == lagging, causes
    assert causes[1]["detail"] == "cannot connect; never ok"  # a device that has a last-ok time keeps it


def test_a_ci_bound_beyond_the_box_prints_as_the_cli_prints_it() -> None:
    """Item 9: the H table showed ``16.6 – > 499.99999999999983``; the CLI's rule prints ``> 500``."""
    from service.serve.numbers import format_bound

    box = [0.1, 499.99999999999983]
    calls = ", ".join(f"fmtBound({v}, {box})" for v in (612.0, 0.01, 16.62))
    got = _run(["fmtSig", "fmtBound"], f"[{calls}]")
    assert got == ["> 500", "< 0.1", "16.6"]
    assert got == [format_bound(612.0, (box[0], box[1])), format_bound(0.01, (box[0], box[1])), "16.6"]
