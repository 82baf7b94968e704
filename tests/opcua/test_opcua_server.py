"""The OPC UA outlet seen by an independent client (asyncua's own client, over loopback TCP) on the real
served service (issue 28 items 2 and 4): the type and the stable string NodeIds, every value with its unit,
EURange, StatusCode and SourceTimestamp, the StatusCodes following REST's verdicts in each state of the
policy (fresh, all data lost, the DAQ lost: predicted, then past the open-loop limit, all lost past the
limit; no data yet), a subscription, and the security rules (anonymous read-only, Sign&Encrypt with a user,
an untrusted certificate refused, writes, calls and node management refused, no None endpoint when
Sign&Encrypt only)."""

from __future__ import annotations

import asyncio
import logging
from datetime import datetime, timedelta
from typing import Any

import numpy as np
import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from service.contracts.verdict import ChtcStatus, Reason, Verdict
from service.serve.opcua.nodes import UNITS_NAMESPACE, VARS, Var
from service.serve.opcua.status import UaStatus, lost_since, status_of
from simulator.served import feed

from .conftest import (
    NS,
    PASSWORD,
    USER,
    Pki,
    Rig,
    daq_lost,
    next_updates,
    node_path,
    opcua_settings,
    start_rig,
    stop_rig,
)

pytestmark = pytest.mark.timeout(180)
# SPEC §7: the UNECE codes, and the UnitId is the code's ASCII bytes as an integer
UNIT_IDS = {"D55": 0x443535, "CEL": 0x43454C, "KEL": 0x4B454C, "4H": 0x3448, "MMT": 0x4D4D54, "C94": 0x433934,
            "NU": 0x4E55, "SEC": 0x534543}  # fmt: skip
COMPENSATION = ("Growth.Axial", "Growth.AxialCiLow95", "Controller.SD43900Mm", "Controller.IsgOffset0p1um")


async def _read_all(client: Client) -> dict[str, ua.DataValue]:
    idx = await client.get_namespace_index(NS)
    nodes = [client.get_node(f"ns={idx};s=Spindle1.{v.path}") for v in VARS]
    values = await client.read_attributes(nodes, ua.AttributeIds.Value)
    return {v.path: dv for v, dv in zip(VARS, values, strict=True)}


def _verdict(body: dict[str, Any]) -> Verdict:
    reason = body["reason_code"]
    return Verdict(
        ChtcStatus(body["status"]), bool(body["usable_for_compensation"]), Reason(reason) if reason else None
    )


def _utc(s: str) -> datetime:
    return datetime.fromisoformat(s.replace("Z", "+00:00"))


def _agrees_with_rest(rig: Rig, got: dict[str, ua.DataValue]) -> UaStatus:
    """The compensation values' StatusCode, Status.* and the growth agree with GET /compensation at the same
    instant (the hand-moved clock does not move between the two reads); returns that StatusCode."""
    body = rig.rest.get("/api/v1/compensation").json()
    verdict = _verdict(body)
    assert got["Status.Text"].Value.Value == body["status"]
    assert got["Status.Usable"].Value.Value is body["usable_for_compensation"]
    assert got["Status.Reason"].Value.Value == (body["reason_code"] or "")
    code = UaStatus(got["Status.Code"].Value.Value)
    v = rig.served.service.view
    now = rig.served.clock()
    lost = lost_since(v.last_good_daq_t, v.last_good_can_t, None if v.newest is None else v.newest.t, now=now)
    bad_after_s = 60.0 * rig.settings.compensation.max_open_loop_min
    assert code is status_of(verdict, lost_s=lost, bad_after_s=bad_after_s)
    for path in COMPENSATION:
        assert got[path].StatusCode_.value == code, path
        assert got[path].SourceTimestamp == _utc(body["at"]), path
    if code >> 30 == 2:  # Bad: asyncua (as most clients) drops the value of a Bad DataValue
        return code
    assert got["Growth.Axial"].Value.Value == pytest.approx(body["axial"]["um"], abs=1e-3)
    assert got["Controller.IsgOffset0p1um"].Value.Value == body["plc"]["isg_temp_comp_offset_0_0p1um"]
    return code


def test_the_type_the_nodeids_and_every_value_with_its_unit_status_and_time(rig: Rig) -> None:
    async def run() -> None:
        async with Client(rig.url) as c:
            idx = await c.get_namespace_index(NS)
            assert idx == 2
            spindle = c.get_node("ns=2;s=Spindle1")
            assert (await spindle.read_type_definition()) == ua.NodeId("SpindleThermalModelType", 2)
            groups = {(await n.read_browse_name()).Name for n in await spindle.get_children()}
            assert {"Status", "H", "Condition", "Temperatures", "Growth", "Controller", "Devices"} <= groups
            growth = c.get_node("ns=2;s=Spindle1.Growth")
            names = {(await n.read_browse_name()).Name for n in await growth.get_children()}
            assert {"Axial", "AxialCiLow95", "AxialCiHigh95", "SteadyAxial", "ForecastAxial"} <= names
            await next_updates(c)
            got = await _read_all(c)
            now = rig.served.clock()
            for var in VARS:
                dv = got[var.path]
                assert dv.SourceTimestamp is not None and dv.SourceTimestamp <= now, var.path
                assert dv.StatusCode_ is not None, var.path
                if var.length:
                    assert isinstance(dv.Value.Value, list), var.path
                    assert var.length < 0 or len(dv.Value.Value) == var.length, var.path
                else:
                    assert not isinstance(dv.Value.Value, list), var.path
                await _check_node(c, var)
            # what REST serves, with its statuses and the data's time
            code = _agrees_with_rest(rig, got)
            assert code is UaStatus.GOOD, "the demo plan ends fresh and usable with a configured zero"
            sensors = rig.rest.get("/api/v1/sensors").json()["channels"]
            measured = got["Temperatures.Measured"]
            want_c = [np.nan if x["measured_c"] is None else x["measured_c"] for x in sensors]
            assert measured.Value.Value == pytest.approx(want_c, abs=1e-3, nan_ok=True)
            assert measured.SourceTimestamp == _utc(sensors[0]["t"])
            zones = rig.rest.get("/api/v1/chtc").json()["zones"]
            assert got["H.Values"].Value.Value == pytest.approx([z["h_w_m2k"] for z in zones], rel=1e-3)
            for i, z in enumerate(zones):
                weak = not z["identified"] or z["prior_dominated"] or z["at_bound"]
                want = UaStatus.UNCERTAIN_SENSOR_NOT_ACCURATE if weak else got["H.Values"].StatusCode_.value
                assert got[f"H.{z['name']}"].StatusCode_.value == want, z["name"]
                assert got["H.Identified"].Value.Value[i] is z["identified"]
            assert got["Status.SampleAge"].Value.Value == pytest.approx(0.0, abs=1e-6)
            assert got["Devices.ModelLoaded"].Value.Value is True

    rig.run(run)


async def _check_node(c: Client, var: Var) -> None:
    node = await node_path(c, var.path)
    assert ua.AccessLevel.CurrentWrite not in await node.get_access_level(), var.path
    historizing = await node.read_attribute(ua.AttributeIds.Historizing)
    assert historizing.Value.Value is False, var.path  # no history is served
    typedef = await node.read_type_definition()
    if var.unit is None:
        assert typedef == ua.NodeId(ua.ObjectIds.BaseDataVariableType), var.path
        return
    assert typedef == ua.NodeId(ua.ObjectIds.AnalogUnitRangeType), var.path
    eu = await (await node.get_child("0:EngineeringUnits")).read_value()
    assert eu.NamespaceUri == UNITS_NAMESPACE and eu.UnitId == UNIT_IDS[var.unit], var.path
    rng = await (await node.get_child("0:EURange")).read_value()
    assert var.range is not None and (rng.Low, rng.High) == var.range, var.path


def test_a_subscription_gets_a_new_sample_within_one_sample_period(rig: Rig) -> None:
    period_s = rig.settings.acquisition.sample_period_s

    class Handler:
        def __init__(self) -> None:
            self.seen: asyncio.Queue[ua.DataValue] = asyncio.Queue()

        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            self.seen.put_nowait(data.monitored_item.Value)

    async def run() -> None:
        async with Client(rig.url) as c:
            h = Handler()
            sub = await c.create_subscription(100, h)
            await sub.subscribe_data_change(await node_path(c, "Status.NewestSampleTime"))
            first = await asyncio.wait_for(h.seen.get(), 10.0)  # the current value at once
            before = first.Value.Value
            await asyncio.to_thread(rig.served.feed_next, 1)
            dv = await asyncio.wait_for(h.seen.get(), period_s)  # one sample period, wall clock
            assert dv.Value.Value > before and dv.SourceTimestamp == dv.Value.Value
            await sub.delete()

    rig.run(run)


async def _user_executable(c: Client) -> list[bool]:
    idx = await c.get_namespace_index(NS)
    out = []
    for name in ("StartIdentification", "TakeSensorBaseline"):
        method = c.get_node(f"ns={idx};s=Spindle1.{name}")
        assert (await method.read_attribute(ua.AttributeIds.Executable)).Value.Value is True
        out.append((await method.read_attribute(ua.AttributeIds.UserExecutable)).Value.Value)
    return out


def test_anonymous_may_read_but_not_write_call_or_add_nodes(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    before = dict(rig.outlet.outlet_metrics().refused)

    async def run() -> None:
        async with Client(rig.url) as c:
            node = await node_path(c, "Growth.Axial")
            for _ in range(5):  # a client that keeps writing: one log line, five counted
                with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
                    await node.write_value(ua.DataValue(ua.Variant(1.0, ua.VariantType.Double)))
            with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
                await c.nodes.objects.add_variable(2, "Injected", 1.0)
            spindle = c.get_node("ns=2;s=Spindle1")
            assert await _user_executable(c) == [False, False]  # what the session may do
            with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
                await spindle.call_method("2:TakeSensorBaseline")
            assert isinstance(await node.read_value(), float)
            level = (await node.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value
            assert level == ua.AccessLevel.CurrentRead.mask

    with caplog.at_level(logging.INFO):
        rig.run(run)
    refused = rig.outlet.outlet_metrics().refused
    assert refused.get("Write", 0) - before.get("Write", 0) == 5
    assert refused.get("AddNodes", 0) - before.get("AddNodes", 0) == 1
    assert refused.get("Call", 0) - before.get("Call", 0) == 1
    asyncua_loud = [
        r for r in caplog.records if r.name.startswith("asyncua.server") and r.levelno >= logging.WARNING
    ]
    assert asyncua_loud == [], [r.getMessage() for r in asyncua_loud]
    lines = [r for r in caplog.records if "refused Write for anonymous" in r.getMessage()]
    assert len(lines) <= 1 and all(r.levelno == logging.INFO for r in lines)  # 0: an earlier test logged it


def _secure(c: Client, pki: Pki, *, rogue: bool = False) -> Any:
    cert, key = (pki.rogue_cert, pki.rogue_key) if rogue else (pki.client_cert, pki.client_key)
    return c.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key), server_certificate=str(pki.server_cert)
    )


def test_an_encrypted_session_with_a_user_reads_and_may_call_but_not_write(rig: Rig, pki: Pki) -> None:
    async def run() -> None:
        c = Client(rig.url)
        await _secure(c, pki)
        c.set_user(USER)
        c.set_password(PASSWORD)
        async with c:
            node = await node_path(c, "Growth.Axial")
            assert isinstance(await node.read_value(), float)
            with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
                await node.write_value(ua.DataValue(ua.Variant(1.0, ua.VariantType.Double)))
            spindle = c.get_node("ns=2;s=Spindle1")
            assert await _user_executable(c) == [True, True]
            try:  # the service answers (a job, or busy/not ready): the call itself is authorised
                result = await spindle.call_method(
                    "2:StartIdentification", ua.Variant("opcua test", ua.VariantType.String)
                )
                assert "job" in result
            except ua.UaStatusCodeError as err:
                assert "BadInvalidState" in str(err)
        bad = Client(rig.url)
        await _secure(bad, pki)
        bad.set_user(USER)
        bad.set_password("not-the-password")
        with pytest.raises(ua.UaStatusCodeError, match=r"BadUserAccessDenied|BadIdentityTokenRejected"):
            async with bad:
                pass

    rig.run(run)


def test_an_untrusted_client_certificate_is_refused(rig: Rig, pki: Pki) -> None:
    async def run() -> None:
        c = Client(rig.url)
        await _secure(c, pki, rogue=True)
        with pytest.raises((ua.UaStatusCodeError, ua.UaError, ConnectionError, TimeoutError)):
            async with c:
                await (await node_path(c, "Growth.Axial")).read_value()

    rig.run(run)


def test_sign_and_encrypt_only_has_no_none_endpoint_and_no_anonymous_channel(tmp_path, pki: Pki) -> None:  # type: ignore[no-untyped-def]
    settings = opcua_settings(
        pki, policies=("Basic256Sha256_SignAndEncrypt",), anonymous=False, methods=False
    )
    r = start_rig(tmp_path, settings, feed=3)
    try:

        async def run() -> None:
            async with Client(r.url):  # discovery over a None channel is allowed, a session is not
                pass

        with pytest.raises((ua.UaStatusCodeError, ua.UaError)):
            r.run(run)

        async def endpoints() -> list[Any]:
            c = Client(r.url)
            return list(await c.connect_and_get_server_endpoints())

        eps = r.run(endpoints)
        assert eps and all(e.SecurityMode == ua.MessageSecurityMode.SignAndEncrypt for e in eps)
        assert all(e.SecurityPolicyUri.endswith("#Basic256Sha256") for e in eps)
        tokens = {t.TokenType for e in eps for t in e.UserIdentityTokens}
        assert ua.UserTokenType.Anonymous not in tokens

        async def secure() -> float:
            c = Client(r.url)
            await _secure(c, pki)
            c.set_user(USER)
            c.set_password(PASSWORD)
            async with c:
                node = await node_path(c, "Status.SampleAge")
                for _ in range(100):  # the first view reaches the address space within update_interval_s
                    dv = await node.read_data_value(raise_on_bad_status=False)
                    if dv.StatusCode.is_good():
                        return float(dv.Value.Value)
                    await asyncio.sleep(0.1)
                raise AssertionError(f"Status.SampleAge never good over a secure session: {dv.StatusCode}")

        assert r.run(secure) >= 0.0
    finally:
        stop_rig(r)


def test_status_codes_follow_rest_when_the_daq_stops_and_when_all_data_stop(tmp_path, pki: Pki) -> None:  # type: ignore[no-untyped-def]
    r = start_rig(tmp_path, opcua_settings(pki))
    served = r.served
    codes: list[tuple[str, str, UaStatus]] = []

    async def observe(label: str) -> None:
        async with Client(r.url) as c:
            await next_updates(c)
            got = await _read_all(c)
            codes.append((label, got["Status.Text"].Value.Value, _agrees_with_rest(r, got)))

    try:
        r.run(lambda: observe("fresh"))
        served.clock.advance(120.0)  # the acquisition stops: nothing at all for 2 min
        r.run(lambda: observe("all lost"))
        last = served.samples[served.fed - 1]
        period = timedelta(seconds=r.settings.acquisition.sample_period_s)
        t = served.clock()
        limit_s = 60.0 * r.settings.compensation.max_open_loop_min
        for i in range(int(limit_s / period.total_seconds())):  # CAN comes back, the DAQ stays silent
            t += period
            feed(served, daq_lost(last, t))
            if i == 1:
                r.run(lambda: observe("daq lost"))
        r.run(lambda: observe("daq lost too long"))
        served.clock.advance(120.0)  # nothing at all again, the DAQ now lost for longer than the limit
        r.run(lambda: observe("all lost too long"))
    finally:
        stop_rig(r)
    assert [(label, text, code) for label, text, code in codes] == [
        ("fresh", "fresh", UaStatus.GOOD),
        ("all lost", "stale", UaStatus.UNCERTAIN_NO_COMMUNICATION_LAST_USABLE_VALUE),
        ("daq lost", "predicted", UaStatus.UNCERTAIN_SUB_NORMAL),
        ("daq lost too long", "predicted", UaStatus.BAD_NO_COMMUNICATION),  # open_loop_too_long
        ("all lost too long", "stale", UaStatus.BAD_NO_COMMUNICATION),  # lost for longer than bad_after_s
    ]


def test_no_sample_yet_waits_for_initial_data_and_sessions_are_bounded(tmp_path, pki: Pki) -> None:  # type: ignore[no-untyped-def]
    r = start_rig(tmp_path, opcua_settings(pki, max_connections=2), feed=0)
    try:

        async def run() -> dict[str, ua.DataValue]:
            first, second, third = Client(r.url), Client(r.url), Client(r.url)
            async with first, second:
                with pytest.raises(ua.UaStatusCodeError, match="BadMaxConnectionsReached"):
                    async with third:
                        pass
                await next_updates(first)
                got = await _read_all(first)
            async with Client(r.url) as fourth:  # a slot is free again
                await next_updates(fourth, 1)
            return got

        got = r.run(run)
        assert r.outlet.outlet_metrics().refused.get("BadMaxConnectionsReached") == 1  # /metrics, not ERROR
    finally:
        stop_rig(r)
    assert got["Status.Text"].Value.Value == "no-data" and got["Status.Usable"].Value.Value is False
    waiting = (
        *COMPENSATION,
        "H.H1",
        "H.Values",
        "Temperatures.Measured",
        "Condition.SpeedRpm",
        "Status.SampleAge",
    )
    for path in waiting:
        assert got[path].StatusCode_.value == UaStatus.BAD_WAITING_FOR_INITIAL_DATA, path
    assert got["Status.Heartbeat"].StatusCode_.value == UaStatus.GOOD
    assert got["Status.Heartbeat"].SourceTimestamp is not None
