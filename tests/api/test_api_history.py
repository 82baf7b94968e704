"""GET /api/v1/sensors/history and GET /api/v1/spindle against the real service."""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime

import numpy as np
import pytest
from fastapi.testclient import TestClient

from drivers.quality import Quality
from model.geometry import load_spindle
from service.serve.sensorhistory import SensorHistoryBuffer
from simulator.served import Served, feed
from tests.api.conftest import ManualClock


def _push(served: Served, n: int) -> list[np.ndarray]:
    """The plan's next n samples (10 s apart, °C), channel 5 open-circuit in the last one."""
    pushed = []
    for k, s in enumerate(served.samples[served.fed : served.fed + n]):
        quality = s.quality.copy()
        if k == n - 1:
            quality[4] = Quality.OPEN_CIRCUIT
        feed(served, replace(s, quality=quality))
        pushed.append(s.temps_c)
    return pushed


def _iso(t: datetime) -> str:
    return t.isoformat().replace("+00:00", "Z")


def test_history_gives_every_sample_with_units_utc_times_and_the_prediction(
    client: TestClient, served: Served, clock: ManualClock
) -> None:
    service = served.service
    before = service.sensor_history(None).t  # the demo plan's samples so far
    assert len(before) == served.fed
    pushed = _push(served, 6)
    body = client.get("/api/v1/sensors/history", params={"channels": "1,5,32"}).json()
    assert body["unit"] == "°C" and body["since"] is None and body["truncated"] is False
    assert len(body["t"]) == len(before) + 6 and all(t.endswith("Z") for t in body["t"])
    assert body["t"][-1] == _iso(clock.now) and body["t"] == sorted(body["t"])
    assert [c["channel"] for c in body["channels"]] == [1, 5, 32]
    ch1, ch5, ch32 = body["channels"]
    spec = load_spindle()
    assert (ch1["name"], ch1["role"]) == (spec.sensors[0].name, "bearing")
    assert ch32["name"] == spec.sensors[31].name
    np.testing.assert_allclose(ch32["measured_c"][-6:], [p[31] for p in pushed], atol=5e-4)
    assert ch5["measured_c"][-1] is None and ch5["measured_c"][-2] is not None  # masked, not dropped
    want = service.sensors()[0].predicted_c  # the live state's prediction for the newest sample
    assert want is not None and ch1["predicted_c"][-1] == pytest.approx(want, abs=5e-4)
    assert all(p is not None for p in ch1["predicted_c"][-6:])


def test_history_since_is_strict_and_limit_keeps_the_newest(client: TestClient, served: Served) -> None:
    _push(served, 5)
    full = client.get("/api/v1/sensors/history").json()
    assert len(full["channels"]) == 32
    since = full["t"][-3]
    later = client.get("/api/v1/sensors/history", params={"since": since}).json()
    assert later["t"] == full["t"][-2:] and later["since"] == since
    newest = client.get("/api/v1/sensors/history", params={"limit": 2, "channels": "7"}).json()
    assert newest["t"] == full["t"][-2:] and newest["truncated"] is True
    assert newest["channels"][0]["measured_c"] == full["channels"][6]["measured_c"][-2:]


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ({"channels": "1,x"}, "channels"),
        ({"channels": "0"}, "channels"),
        ({"channels": "33"}, "channels"),
        ({"since": "2026-11-22T08:00:00"}, "since"),  # no zone
        ({"since": "yesterday"}, "since"),
        ({"limit": "0"}, "limit"),
        ({"limit": "10001"}, "limit"),
    ],
)
def test_history_rejects_bad_parameters_naming_the_field(
    ro_client: TestClient, query: dict, field: str
) -> None:
    r = ro_client.get("/api/v1/sensors/history", params=query)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "invalid" and err["field"] == field and err["message"].startswith(field)


def test_channels_outside_1_to_32_or_empty_are_refused_by_the_documented_pattern(
    ro_client: TestClient,
) -> None:
    """The OpenAPI pattern is the contract (as for /sensors): an empty list was schema-valid but a 422."""
    op = ro_client.get("/api/v1/openapi.json").json()["paths"]["/api/v1/sensors/history"]["get"]
    schema = next(p for p in op["parameters"] if p["name"] == "channels")["schema"]
    assert "pattern" in str(schema), schema
    for bad in ("2,40", "", "1,,2"):
        err = ro_client.get("/api/v1/sensors/history", params={"channels": bad}).json()["error"]
        assert err["field"] == "channels" and err["message"].startswith("channels"), (bad, err)


def test_history_buffer_keeps_the_last_capacity_samples_in_order() -> None:
    buf = SensorHistoryBuffer(3, [(1, "a", "bearing"), (2, "b", "housing")])
    t0 = datetime.fromisoformat("2026-11-22T08:00:00+00:00")
    assert buf.since(None).t == () and buf.since(None).measured_c.shape == (0, 2)
    times = [t0.replace(second=k) for k in range(5)]
    for k, t in enumerate(times):
        buf.append(t, np.array([k, -k], dtype=float), None if k < 2 else np.array([10.0 + k, 20.0]))
    h = buf.since(None)
    assert h.t == tuple(times[2:])
    np.testing.assert_array_equal(h.measured_c[:, 0], [2, 3, 4])
    np.testing.assert_array_equal(h.predicted_c[:, 0], [12, 13, 14])
    assert buf.since(times[3]).t == (times[4],)
    with pytest.raises(ValueError, match="capacity"):
        SensorHistoryBuffer(0, [])


def test_spindle_lists_the_named_parts_and_zones_of_the_spindle_description(ro_client: TestClient) -> None:
    body = ro_client.get("/api/v1/spindle").json()
    spec = load_spindle()
    names = [p["name"] for p in body["parts"]]
    assert names == [r.name for r in spec.regions]
    assert {"pulley", "housing", "front_end_cap", "rear_end_cap", "shaft_body"} <= set(names)
    housing = body["parts"][names.index("housing")]
    assert housing["r0_m"] < housing["r1_m"] and housing["z0_m"] < housing["z1_m"]
    assert [z["name"] for z in body["zones"]] == [f"H{i}" for i in range(1, 8)]
    assert [z["description"] for z in body["zones"]] == [z.description for z in spec.zones]
    assert "pulley" in body["zones"][0]["description"]
