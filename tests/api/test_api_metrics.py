"""GET /metrics: Prometheus text that parses, with the service's numbers and the API's own latency."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from api.app import create_app
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import Served
from tests.api.conftest import ManualClock


def _families(client: TestClient) -> dict[str, list]:  # type: ignore[type-arg]
    r = client.get("/api/v1/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    return {f.name: f.samples for f in text_string_to_metric_families(r.text)}


def test_metrics_parse_and_carry_service_numbers(
    client: TestClient, service: SoftSensorService, clock: ManualClock
) -> None:
    clock.advance(7.0)
    fam = _families(client)
    ages = [s for s in fam["chtc_channel_age_seconds"]]
    assert len(ages) == 32 and all(abs(s.value - 7.0) < 1e-9 for s in ages)
    m = service.metrics()
    count = [s for s in fam["chtc_identification_duration_seconds"] if s.name.endswith("_count")]
    assert count[0].value == m.identification_duration_s.count == 2  # one per condition
    total = {s.labels["outcome"]: s.value for s in fam["chtc_identifications"] if s.name.endswith("_total")}
    assert total["ok"] == 2.0 and total == {k: float(v) for k, v in m.identifications_total.items()}
    fit = fam["chtc_identification_fit"][0].value
    assert fit == m.last_fit
    # the live state's Kalman filter: the last sample's NIS over its channels, converged and consistent
    f = m.filter
    assert f is not None and f.dof == fam["chtc_filter_nis_dof"][0].value > 0
    assert fam["chtc_filter_nis"][0].value == f.nis > 0.0
    assert fam["chtc_filter_converged"][0].value == 1.0 and fam["chtc_filter_consistent"][0].value == 1.0
    verdicts = {s.labels["verdict"]: s.value for s in fam["chtc_filter_nis_verdict"]}
    assert sum(verdicts.values()) == 1.0 and verdicts[f.verdict] == 1.0 and verdicts["high"] == 0.0


def test_request_latency_histogram_counts_requests(ro_client: TestClient) -> None:
    for _ in range(3):
        ro_client.get("/api/v1/chtc")
    ro_client.get("/api/v1/identifications/999")
    fam = _families(ro_client)
    counts = {
        (s.labels["route"], s.labels["status"]): s.value
        for s in fam["chtc_http_request_duration_seconds"]
        if s.name.endswith("_count")
    }
    assert counts[("/api/v1/chtc", "200")] == 3
    assert counts[("/api/v1/identifications/{identification_id}", "404")] == 1


def test_each_app_has_its_own_registry(ro_service: SoftSensorService, ro_clock: ManualClock) -> None:
    from api.app import create_app
    from service.settings import Settings

    a = create_app(Settings(), ro_service, clock=ro_clock)
    b = create_app(Settings(), ro_service, clock=ro_clock)
    assert a.state.metrics.registry is not b.state.metrics.registry


def test_every_sample_is_labelled_with_the_spindle(
    ro_service: SoftSensorService, ro_clock: ManualClock
) -> None:
    from api.app import create_app
    from service.settings import Settings

    settings = Settings.model_validate({"spindle": {"id": "cell3-s7"}})
    with TestClient(create_app(settings, ro_service, clock=ro_clock)) as client:
        client.get("/api/v1/chtc")  # a request latency sample too
        fam = _families(client)
    samples = [s for values in fam.values() for s in values]
    assert len(fam) > 20 and samples
    assert {s.labels.get("spindle") for s in samples} == {"cell3-s7"}
    # the other labels are kept beside it
    assert {s.labels["zone"] for s in fam["chtc_h_w_m2k"]} == {f"H{i}" for i in range(1, 8)}


def test_h_gauges_status_usable_and_build_info(
    client: TestClient, service: SoftSensorService, clock: ManualClock
) -> None:
    fam = _families(client)
    snap = service.chtc()
    assert snap is not None
    for name, values in (
        ("chtc_h_w_m2k", snap.h),
        ("chtc_h_ci95_lo_w_m2k", snap.ci95_lo),
        ("chtc_h_ci95_hi_w_m2k", snap.ci95_hi),
        ("chtc_h_identified", snap.identified),
    ):
        got = {s.labels["zone"]: s.value for s in fam[name]}
        assert got == {z: float(v) for z, v in zip(snap.zones, values, strict=True)}, name
    status = {s.labels["status"]: s.value for s in fam["chtc_status"]}
    assert status == {
        "fresh": 0.0,
        "predicted": 0.0,
        "identifying": 0.0,
        "stale": 0.0,
        "converging": 0.0,
        "at-bound": 0.0,
        "no-data": 0.0,
        str(snap.status): 1.0,
    }
    assert fam["chtc_usable_for_compensation"][0].value == float(snap.usable_for_compensation)
    info = fam["chtc_build_info"][0]
    assert info.name == "chtc_build_info" and info.value == 1.0
    assert info.labels["model_version"] == snap.model_version and info.labels["version"]
    clock.advance(3600.0)  # no data for an hour: stale, not usable
    fam = _families(client)
    assert {s.labels["status"]: s.value for s in fam["chtc_status"]}["stale"] == 1.0
    assert fam["chtc_usable_for_compensation"][0].value == 0.0
    # the reason is named in the metrics too (issue 12 "Done when"), as bounded codes
    snap = service.chtc()
    assert snap is not None and snap.reason
    assert {s.labels["code"]: s.value for s in fam["chtc_not_usable_reason"]} == {
        snap.reason.split(":")[0]: 1.0
    }
    ready = service.ready()
    assert fam["chtc_ready"][0].value == float(ready.ready)
    codes = {s.labels["code"] for s in fam["chtc_not_ready_reason"]}
    assert codes == {x.split(":")[0].strip() for x in ready.reasons} and (ready.ready or codes)


@pytest.mark.slow  # over ~5 s alone (issue 25: the fast subset under 5 min)
def test_outcome_and_event_counters_are_separate(served_devices_down: Served) -> None:
    """Real drivers: the DAQ's refused connects are poll outcomes, the CAN sensor's silence is an event."""
    s = served_devices_down
    with TestClient(create_app(Settings(), s.service, clock=s.clock)) as client:
        fam = _families(client)
    m = s.service.metrics()
    for device, outcome_family in (("modbus", "chtc_modbus_polls"), ("can", "chtc_can_frames")):
        events = {
            x.labels["event"]: x.value for x in fam[f"chtc_{device}_events"] if x.name.endswith("_total")
        }
        want = m.modbus_events_total if device == "modbus" else m.can_events_total
        assert events == {k: float(v) for k, v in want.items()}
        outcomes = {x.labels["outcome"]: x.value for x in fam[outcome_family] if x.name.endswith("_total")}
        assert outcomes.keys().isdisjoint(events)
    polls = {x.labels["outcome"]: x.value for x in fam["chtc_modbus_polls"] if x.name.endswith("_total")}
    assert polls == {"ok": 0.0, "link_down": 1.0, "device_unavailable": 1.0}
    silence = {x.labels["event"]: x.value for x in fam["chtc_can_events"] if x.name.endswith("_total")}
    assert silence == {"device_timeout": 2.0}


def test_an_outlet_that_counts_shows_on_metrics(
    client: TestClient, service: SoftSensorService, tmp_path: Path
) -> None:
    """The MQTT outlet's counters (service.serve.interface.CountedOutlet) reach /metrics as chtc_outlet_*;
    never started here (no broker): nothing sent, not connected."""
    from service.mqttsettings import MqttSettings
    from service.serve.mqtt.outlet import MqttOutlet

    outlet = MqttOutlet(MqttSettings(enabled=True).for_spindle("spindle1"), state_dir=tmp_path)
    service.subscribe(outlet)
    try:
        fam = _families(client)
    finally:
        service.unsubscribe(outlet)
    sent = {s.labels["result"]: s.value for s in fam["chtc_outlet_messages"] if s.labels["outlet"] == "mqtt"}
    assert sent == {"sent": 0.0, "dropped": 0.0}
    assert fam["chtc_outlet_buffered"][0].value == 0.0
    assert fam["chtc_outlet_connected"][0].value == 0.0
    assert "chtc_outlet_messages" not in _families(client)  # unsubscribed: gone
