"""The OPC UA outlet's pure parts: the verdict -> StatusCode table (every status and reason of the policy),
the UNECE UnitIds, the password hashes and users, the read-only rules, the settings, and the exported
NodeSet2 (loaded back into a fresh server as TIA Portal or TwinCAT would import it)."""

from __future__ import annotations

import asyncio
import socket
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from asyncua import Server, ua
from asyncua.server.users import User, UserRole

from service.cli import main as chtc
from service.contracts.verdict import ChtcStatus, Reason, Verdict
from service.host.runtime import enabled_outlets
from service.mqttsettings import MqttSettings
from service.serve.errors import OutletError
from service.serve.opcua.nodes import VARS, unit_id
from service.serve.opcua.security import (
    HashedUserManager,
    ReadOnlyRules,
    hash_password,
    load_users,
    verify_password,
)
from service.serve.opcua.status import UaStatus, lost_since, status_of, worst
from service.settings import Settings, SettingsError

S = ChtcStatus
LOST, BAD_AFTER = 30.0, 600.0


@pytest.mark.parametrize(
    ("verdict", "want"),
    [
        (Verdict(S.FRESH, True), UaStatus.GOOD),
        (Verdict(S.NO_DATA, False, Reason.NO_DATA), UaStatus.BAD_WAITING_FOR_INITIAL_DATA),
        (Verdict(S.IDENTIFYING, False, Reason.CONDITION_CHANGED), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.IDENTIFYING, False, Reason.SPEED_NOT_VISITED), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.IDENTIFYING, False, Reason.MAP_OLD), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.PREDICTED, True), UaStatus.UNCERTAIN_SUB_NORMAL),
        (Verdict(S.PREDICTED, False, Reason.NO_REFERENCE), UaStatus.UNCERTAIN_SUB_NORMAL),
        (Verdict(S.PREDICTED, False, Reason.OPEN_LOOP_TOO_LONG), UaStatus.BAD_NO_COMMUNICATION),
        (Verdict(S.AT_BOUND, False, Reason.AT_BOUND), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.FRESH, False, Reason.NOT_IDENTIFIED), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.FRESH, False, Reason.CI_TOO_WIDE), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.FRESH, False, Reason.NO_REFERENCE), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.FRESH, False, Reason.MECHANICS_UNCALIBRATED), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.STALE, False, Reason.STATE_INCONSISTENT), UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE),
        (Verdict(S.CONVERGING, False, Reason.STATE_CONVERGING), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.STALE, False, Reason.RESTORED), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.FRESH, False, Reason.IDENTIFICATION_OLD), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.FRESH, False, Reason.NO_IDENTIFICATION), UaStatus.UNCERTAIN_LAST_USABLE_VALUE),
        (Verdict(S.STALE, False, Reason.STALE), UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE),
        (Verdict(S.STALE, False, Reason.CORE_BEHIND), UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE),
    ],
    ids=lambda x: x.name if isinstance(x, UaStatus) else f"{x.status.value}/{x.reason}",
)
def test_every_verdict_maps_to_its_status_code(verdict: Verdict, want: UaStatus) -> None:
    assert status_of(verdict, lost_s=LOST, bad_after_s=BAD_AFTER) is want


def test_every_reason_is_mapped_and_lost_data_turns_bad_past_the_limit() -> None:
    for reason in Reason:  # no reason falls through to Good
        code = status_of(Verdict(S.STALE, False, reason), lost_s=LOST, bad_after_s=BAD_AFTER)
        assert code is not UaStatus.GOOD, reason
    stale = Verdict(S.STALE, False, Reason.STALE)
    assert status_of(stale, lost_s=BAD_AFTER + 1, bad_after_s=BAD_AFTER) is UaStatus.BAD_NO_COMMUNICATION
    # SPEC §7's hex values
    assert [int(c) for c in UaStatus] == [
        0, 0x40900000, 0x40930000, 0x40950000, 0x408F0000, 0x80310000, 0x80320000
    ]  # fmt: skip
    assert worst(UaStatus.GOOD, UaStatus.UNCERTAIN_SUB_NORMAL) is UaStatus.UNCERTAIN_SUB_NORMAL
    assert worst(UaStatus.UNCERTAIN_LAST_USABLE_VALUE, UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE) is (
        UaStatus.UNCERTAIN_LAST_USABLE_VALUE
    )
    now = datetime(2026, 1, 1, tzinfo=UTC)
    assert lost_since(now - timedelta(seconds=5), now - timedelta(seconds=50), now=now) == 50.0
    assert lost_since(None, now, now=now) == float("inf")


def test_unit_ids_are_the_unece_codes_ascii_bytes() -> None:
    assert unit_id("CEL") == 4408652 and unit_id("4H") == 13384 and unit_id("D55") == 0x443535
    analog = [v for v in VARS if v.unit is not None]
    assert {v.unit for v in analog} == {"D55", "CEL", "KEL", "4H", "MMT", "C94", "NU", "SEC"}
    assert all(v.range is not None and v.range[0] < v.range[1] for v in analog)
    assert len({v.path for v in VARS}) == len(VARS)


def test_passwords_are_hashed_and_users_checked() -> None:
    stored = hash_password("correct horse battery", iterations=1000)
    assert stored.startswith("pbkdf2_sha256$1000$") and "correct" not in stored
    assert verify_password("correct horse battery", stored)
    assert not verify_password("wrong", stored) and not verify_password("x", "garbage")
    assert hash_password("same", iterations=1000) != hash_password("same", iterations=1000)  # salted
    users = HashedUserManager({"plc": stored}, anonymous=False)
    assert users.get_user(None, username="plc", password="correct horse battery") == User(
        role=UserRole.User, name="plc"
    )
    assert users.get_user(None, username="plc", password="wrong") is None
    assert users.get_user(None, username="nobody", password="x") is None
    assert users.get_user(None) is None  # anonymous off
    assert HashedUserManager({}, anonymous=True).get_user(None) == User(role=UserRole.Anonymous)
    secure_only = HashedUserManager(
        {"plc": stored}, anonymous=True, require_trusted=True, trusted=frozenset({b"x"})
    )
    assert secure_only.get_user(None) is None  # no secure channel: no session
    assert secure_only.get_user(None, certificate=b"x") == User(role=UserRole.Anonymous)


def test_users_are_validated_and_admin_is_refused(tmp_path: Path) -> None:
    good = hash_password("a-long-password", iterations=1000)
    path = tmp_path / "users.toml"
    path.write_text(f'[users]\nplc2 = "{good}"\n', encoding="utf-8")
    assert set(load_users({"plc1": good}, path)) == {"plc1", "plc2"}
    with pytest.raises(OutletError, match="not a pbkdf2_sha256 hash"):
        load_users({"plc": "plaintext"}, None)
    with pytest.raises(OutletError, match="admin"):
        load_users({"Admin": good}, None)


def test_the_rules_allow_reading_and_deny_writes_and_node_management() -> None:
    rules = ReadOnlyRules()
    anon, user = User(role=UserRole.Anonymous), User(role=UserRole.User, name="plc")

    def req(name: str) -> ua.NodeId:
        return ua.NodeId(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))

    for name in ("Read", "Browse", "CreateSubscription", "CreateMonitoredItems", "Publish", "RegisterNodes"):
        assert rules.check_validity(anon, req(name), b"") and rules.check_validity(user, req(name), b""), name
    for name in ("Write", "AddNodes", "DeleteNodes", "AddReferences", "DeleteReferences", "HistoryUpdate"):
        assert not rules.check_validity(user, req(name), b""), name
        assert not rules.check_validity(anon, req(name), b""), name
    assert rules.check_validity(user, req("Call"), b"") and not rules.check_validity(anon, req("Call"), b"")
    assert not rules.check_validity(User(role=UserRole.Admin), req("Read"), b"")


def test_settings_off_by_default_and_sign_encrypt_needs_its_files() -> None:
    s = Settings()
    assert s.opcua.enabled is False and s.opcua.host == "127.0.0.1" and s.opcua.security_policies == ("None",)
    assert enabled_outlets(s, api=True) == ["rest"]
    assert enabled_outlets(Settings(opcua={"enabled": True}), api=True) == ["rest", "opcua"]  # type: ignore[arg-type]
    with pytest.raises(SettingsError, match="needs certificate, private_key, trust_dir"):
        Settings.from_toml(None, opcua={"security_policies": ["Basic256Sha256_SignAndEncrypt"]})
    redacted = Settings(opcua={"users": {"plc": hash_password("x", iterations=1000)}}).redacted()  # type: ignore[arg-type]
    assert redacted["opcua"]["users"] == {"plc": "**********"}


def test_the_exported_nodeset_loads_into_a_fresh_server(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "chtc.NodeSet2.xml"
    config = tmp_path / "chtc.toml"
    config.write_text('[spindle]\nid = "Spindle1"\n', encoding="utf-8")  # the NodeIds follow spindle.id
    assert chtc(["opcua", "nodeset", "--out", str(out), "--config", str(config)]) == 0
    text = out.read_text(encoding="utf-8")
    assert "<Uri>urn:spindle-chtc:opcua</Uri>" in text and 'BrowseName="1:SpindleThermalModelType"' in text

    async def load() -> tuple[object, object, object]:
        server = Server()
        await server.init()
        await server.import_xml(str(out))
        idx = await server.get_namespace_index("urn:spindle-chtc:opcua")
        axial = server.get_node(f"ns={idx};s=Spindle1.Growth.Axial")
        eu = await (await axial.get_child("0:EngineeringUnits")).read_value()
        typedef = await server.get_node(f"ns={idx};s=Spindle1").read_type_definition()
        return await axial.read_data_type(), eu, typedef

    dtype, eu, typedef = asyncio.run(load())
    assert dtype == ua.NodeId(ua.ObjectIds.Double)
    assert eu.UnitId == unit_id("4H")  # type: ignore[attr-defined]
    assert typedef.Identifier == "SpindleThermalModelType"  # type: ignore[attr-defined]
    assert chtc(["opcua", "user", "admin", "--password-stdin"]) == 2
    assert "admin" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("toml", "prefix"),
    [
        ("", "spindle1"),  # the default spindle id
        ('[spindle]\nid = "cell3-sp07"\n', "cell3-sp07"),  # a plant's id, '-' included
        ('[spindle]\nid = "cell3-sp07"\n[opcua]\nspindle = "Spindle1"\n', "Spindle1"),  # set explicitly
    ],
)
def test_the_node_ids_follow_the_spindle_id_unless_set(tmp_path: Path, toml: str, prefix: str) -> None:
    config = tmp_path / "chtc.toml"
    config.write_text(toml, encoding="utf-8")
    out = tmp_path / "chtc.NodeSet2.xml"
    assert chtc(["opcua", "nodeset", "--out", str(out), "--config", str(config)]) == 0

    async def browse() -> tuple[str, list[str]]:
        server = Server()
        await server.init()
        await server.import_xml(str(out))
        idx = await server.get_namespace_index("urn:spindle-chtc:opcua")
        spindle = server.get_node(f"ns={idx};s={prefix}")
        name = (await spindle.read_browse_name()).Name
        h1 = server.get_node(f"ns={idx};s={prefix}.H.H1")
        return name, [(await h1.read_browse_name()).Name]

    assert asyncio.run(browse()) == (prefix, ["H1"])


def test_the_opcua_and_sparkplug_names_resolve_from_the_spindle_id() -> None:

    s = Settings(spindle={"id": "cell3-sp07"})  # type: ignore[arg-type]
    assert s.opcua.spindle is None and s.opcua.for_spindle(s.spindle.id).node_prefix == "cell3-sp07"
    with pytest.raises(ValueError, match=r"opcua\.spindle"):
        _ = s.opcua.node_prefix  # unresolved: no silent default
    mqtt = s.mqtt.for_spindle(s.spindle.id)
    assert mqtt.device == "cell3-sp07" and mqtt.effective_client_id == "chtc-chtc-1"
    json_mode = MqttSettings(mode="json").for_spindle("cell3-sp07")
    assert json_mode.effective_client_id == "chtc-cell3-sp07"
    explicit = MqttSettings(device_id="press-2").for_spindle("cell3-sp07")
    assert explicit.device == "press-2"
    with pytest.raises(SettingsError, match="device_id"):
        Settings.from_toml(None, mqtt={"device_id": "a/b"})
    hosted = [
        {"id": "sp-a"},
        {"id": "sp-b", "modbus": {"port": 5021}, "can": {"channel": "chtc-b"}},
    ]
    for per in Settings(spindles=hosted).per_spindle():  # type: ignore[arg-type]
        assert per.opcua.for_spindle(per.spindle.id).node_prefix == per.spindle.id
        assert per.mqtt.for_spindle(per.spindle.id).device == per.spindle.id


@pytest.mark.parametrize(
    ("setting", "content", "message"),
    [
        ("certificate", None, "opcua.certificate: cannot read"),
        ("certificate", b"not a certificate", "opcua.certificate: "),
        (
            "private_key",
            b"-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n",
            "opcua.private_key: ",
        ),
    ],
)
def test_an_unreadable_certificate_is_one_line_before_the_model_loads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], setting: str, content: bytes | None, message: str
) -> None:
    path = tmp_path / f"{setting}.pem"
    if content is not None:
        path.write_bytes(content)
    config = tmp_path / "chtc.toml"
    with socket.socket() as s:  # a free port for the API (checked before the OPC UA files)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    config.write_text(
        f'[api]\nport = {port}\n[database]\nurl = "sqlite:///{tmp_path / "db.sqlite"}"\n'
        f'[opcua]\nenabled = true\nport = {port}\n{setting} = "{path}"\n',
        encoding="utf-8",
    )
    t0 = time.monotonic()
    assert chtc(["run", "--config", str(config)]) == 2
    assert time.monotonic() - t0 < 5.0  # the model (about 10 s) was not loaded
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
