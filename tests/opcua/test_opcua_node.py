"""The OPC UA outlet seen by node-opcua's client (npm ``node-opcua``, an independent implementation; issue 28
item 4), driven by ``tests/opcua/node/peer.mjs`` in a Node process: browse, values with their units, EURange,
StatusCodes and SourceTimestamps as REST serves them, a subscription, an encrypted session with a user, and
an untrusted certificate and a write refused. Needs Node and ``npm ci`` in tests/opcua/node (.ci/run does
it); skipped with the reason otherwise."""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

from service.serve.opcua.nodes import UNITS_NAMESPACE
from service.serve.opcua.status import UaStatus
from tests.conftest import IN_CI

from .conftest import NODE_URI, NS, PASSWORD, USER, Pki, Rig, daq_lost, opcua_settings, start_rig, stop_rig

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
HAVE_PEER = NODE is not None and (NODE_DIR / "node_modules" / "node-opcua").is_dir()
pytestmark = pytest.mark.timeout(180)


@pytest.fixture(autouse=True)
def _peer_installed() -> None:
    """Skipped without Node and ``npm ci`` here; in CI (``CI=true``, .ci/run installs them) a failure."""
    if not HAVE_PEER:
        if IN_CI:
            pytest.fail("node-opcua not installed in tests/opcua/node (required in CI: .ci/run runs npm ci)")
        pytest.skip("needs node and `npm ci` in tests/opcua/node (.ci/run installs them)")


PATHS = [
    "Status.Usable",
    "Status.Text",
    "Status.Code",
    "Status.Heartbeat",
    "Status.SampleAge",
    "Status.NewestSampleTime",
    "H.H1",
    "H.Values",
    "Condition.SpeedRpm",
    "Temperatures.Measured",
    "Growth.Axial",
    "Controller.CorrectionUm",
    "Controller.SD43900Mm",
    "Controller.SD42960Mm",
    "Controller.IsgOffset0p1um",
]
UNITS = {"Growth.Axial": 0x3448, "Controller.SD43900Mm": 0x4D4D54, "Condition.SpeedRpm": 0x433934,
         "Temperatures.Measured": 0x43454C, "H.H1": 0x443535, "Status.SampleAge": 0x534543}  # fmt: skip


@pytest.fixture(scope="module")
def node_rig(tmp_path_factory: pytest.TempPathFactory, pki: Pki) -> Iterator[Rig]:
    r = start_rig(tmp_path_factory.mktemp("opcua-node"), opcua_settings(pki))
    yield r
    stop_rig(r)


def _peer(rig: Rig, tmp: Path, **cfg: Any) -> subprocess.Popen[str]:
    args = {"url": rig.url, "nsUri": NS, "pki": str(tmp / "node-pki"), **cfg}
    assert NODE is not None
    return subprocess.Popen(
        [NODE, str(NODE_DIR / "peer.mjs"), json.dumps(args)],
        cwd=NODE_DIR,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _run(rig: Rig, tmp: Path, **cfg: Any) -> dict[str, Any]:
    proc = _peer(rig, tmp, **cfg)
    out, err = proc.communicate(timeout=120)
    lines = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
    assert lines, f"node peer printed nothing (rc {proc.returncode}): {err[-2000:]}"
    return lines[-1]


def _secure(pki: Pki, *, rogue: bool = False) -> dict[str, str]:
    cert, key = (pki.node_rogue_cert, pki.node_rogue_key) if rogue else (pki.node_cert, pki.node_key)
    return {"cert": str(cert), "key": str(key), "applicationUri": NODE_URI}


def _utc(s: str) -> datetime:
    return datetime.fromisoformat(s.replace("Z", "+00:00"))


def test_node_opcua_browses_and_reads_values_units_statuses_and_times(node_rig: Rig, tmp_path: Path) -> None:
    got = _run(node_rig, tmp_path, mode="read", paths=PATHS, units=list(UNITS))
    assert "error" not in got, got
    assert {"Status", "H", "Condition", "Temperatures", "Growth", "Controller", "Devices"} <= set(
        got["browse"]
    )
    body = node_rig.rest.get("/api/v1/compensation").json()
    v = got["values"]
    assert v["Status.Usable"]["value"] is body["usable_for_compensation"] is True
    assert v["Status.Text"]["value"] == body["status"] == "fresh"
    assert v["Status.Code"]["value"] == UaStatus.GOOD
    for path in (
        "Growth.Axial",
        "Controller.CorrectionUm",
        "Controller.SD43900Mm",
        "Controller.IsgOffset0p1um",
    ):
        assert v[path]["status"] == UaStatus.GOOD, path
        assert _utc(v[path]["sourceTimestamp"]) == _utc(body["at"]), path
    assert v["Growth.Axial"]["value"] == pytest.approx(body["axial"]["um"], abs=1e-3)
    assert v["Controller.SD43900Mm"]["value"] == pytest.approx(
        body["plc"]["sd43900_temp_comp_abs_value_mm"], abs=1e-6
    )
    assert v["Controller.SD42960Mm"]["value"] == pytest.approx(
        body["plc"]["sd42960_tool_temp_comp_mm"], abs=1e-6
    )
    assert v["Controller.IsgOffset0p1um"]["value"] == body["plc"]["isg_temp_comp_offset_0_0p1um"]
    assert len(v["Temperatures.Measured"]["value"]) == 32 and len(v["H.Values"]["value"]) == 7
    assert v["H.H1"]["status"] in {UaStatus.GOOD, UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE}
    assert _utc(v["Status.NewestSampleTime"]["value"]) == _utc(body["newest_sample_at"])
    for path, unit_id in UNITS.items():
        u = got["units"][path]
        assert u["namespaceUri"] == UNITS_NAMESPACE and u["unitId"] == unit_id, path
        assert u["low"] < u["high"], path
    assert got["write"] == "BadUserAccessDenied"  # anonymous, and no variable is writable anyway


def test_node_opcua_subscription_gets_a_new_sample_within_one_sample_period(
    node_rig: Rig, tmp_path: Path
) -> None:
    period_s = node_rig.settings.acquisition.sample_period_s
    proc = _peer(
        node_rig, tmp_path, mode="subscribe", paths=["Status.NewestSampleTime"], changes=2, timeoutMs=30000
    )
    assert proc.stdout is not None
    lines: list[dict[str, Any]] = []
    got_first, got_second = threading.Event(), threading.Event()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("{"):
                lines.append(json.loads(line))
                changes = [x for x in lines if "change" in x]
                if len(changes) >= 1:
                    got_first.set()
                if len(changes) >= 2:
                    got_second.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        assert got_first.wait(60.0), lines  # the current value when the item is created
        node_rig.served.feed_next(1)
        assert got_second.wait(period_s), lines  # the new sample's, within one sample period
    finally:
        proc.wait(timeout=60)
    first, second = [x["change"] for x in lines if "change" in x][:2]
    assert _utc(second["value"]) > _utc(first["value"])
    assert second["status"] == UaStatus.GOOD and _utc(second["sourceTimestamp"]) == _utc(second["value"])


def test_node_opcua_encrypted_session_with_a_user(node_rig: Rig, tmp_path: Path, pki: Pki) -> None:
    got = _run(node_rig, tmp_path, mode="connect", security=_secure(pki), user=USER, password=PASSWORD)
    assert got == {"connected": True, "read": "Good"}
    wrong = _run(
        node_rig, tmp_path, mode="connect", security=_secure(pki), user=USER, password="wrong-password"
    )
    assert "error" in wrong and "connected" not in wrong


def test_node_opcua_untrusted_certificate_is_refused(node_rig: Rig, tmp_path: Path, pki: Pki) -> None:
    got = _run(
        node_rig, tmp_path, mode="connect", security=_secure(pki, rogue=True), user=USER, password=PASSWORD
    )
    assert "error" in got and "connected" not in got, got


def test_node_opcua_sees_the_status_codes_change_when_the_daq_stops(tmp_path: Path, pki: Pki) -> None:
    """The DAQ stops answering while CAN keeps coming (the acquisition's stale sample): REST turns
    ``predicted`` and node-opcua reads Uncertain_SubNormal on the growth, then, with nothing at all for two
    minutes, ``stale`` and Uncertain_NoCommunicationLastUsableValue."""
    import time
    from datetime import timedelta

    from simulator.served import feed

    r = start_rig(tmp_path / "rig", opcua_settings(pki))
    paths = ["Status.Text", "Status.Code", "Status.Usable", "Growth.Axial"]
    refresh_s = 2.5 * r.settings.opcua.refresh_s  # the address space re-evaluates ages this often
    try:
        seen = []
        got = _run(r, tmp_path, mode="read", paths=paths, units=[])
        seen.append((r.rest.get("/api/v1/compensation").json()["status"], got["values"]))
        last = r.served.samples[r.served.fed - 1]
        t = r.served.clock()
        for _ in range(2):
            t += timedelta(seconds=r.settings.acquisition.sample_period_s)
            feed(r.served, daq_lost(last, t))
        time.sleep(refresh_s)
        got = _run(r, tmp_path, mode="read", paths=paths, units=[])
        seen.append((r.rest.get("/api/v1/compensation").json()["status"], got["values"]))
        r.served.clock.advance(120.0)  # nothing at all now
        time.sleep(refresh_s)
        got = _run(r, tmp_path, mode="read", paths=paths, units=[])
        seen.append((r.rest.get("/api/v1/compensation").json()["status"], got["values"]))
    finally:
        stop_rig(r)
    summary = [(rest, v["Status.Text"]["value"], v["Growth.Axial"]["status"]) for rest, v in seen]
    assert summary == [
        ("fresh", "fresh", UaStatus.GOOD),
        ("predicted", "predicted", UaStatus.UNCERTAIN_SUB_NORMAL),
        ("stale", "stale", UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE),
    ], summary
