"""Read endpoints against the in-memory service: values, units, timestamps, ETag, statuses."""

from __future__ import annotations

import json
from datetime import datetime

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.serve.interface import ZONE_NAMES
from service.serve.interface_memory import PAPER_H_4000, InMemoryService, push_noisy_sample
from service.settings import Settings
from tests.api.conftest import ManualClock


def test_chtc_returns_current_h_with_units_ci_and_provenance(
    client: TestClient, service: InMemoryService
) -> None:
    r = client.get("/api/v1/chtc")
    assert r.status_code == 200
    body = r.json()
    snap = service.chtc()
    assert snap is not None
    assert body["unit"] == "W/(m²·K)"
    assert [z["name"] for z in body["zones"]] == list(ZONE_NAMES)
    np.testing.assert_allclose([z["h_w_m2k"] for z in body["zones"]], PAPER_H_4000)
    np.testing.assert_allclose([z["ci95_lo_w_m2k"] for z in body["zones"]], snap.ci95_lo, atol=1e-4)
    np.testing.assert_allclose([z["ci95_hi_w_m2k"] for z in body["zones"]], snap.ci95_hi, atol=1e-4)
    assert [z["identified"] for z in body["zones"]] == snap.identified.tolist()
    assert body["status"] == "fresh"
    assert body["identification_id"] == snap.identification_id
    assert body["condition"]["speed_rpm"] == snap.condition.speed_rpm
    assert body["rmse_c"] == pytest.approx(snap.rmse_c)
    assert body["fit"] == pytest.approx(1 / (1 + snap.f))
    assert body["identified_at"].endswith("Z")
    assert datetime.fromisoformat(body["newest_sample_at"]) == snap.newest_sample_at


def test_chtc_sample_age_follows_the_clock(client: TestClient, clock: ManualClock) -> None:
    clock.advance(3.5)
    assert client.get("/api/v1/chtc").json()["sample_age_s"] == pytest.approx(3.5)


def test_chtc_etag_gives_304_until_something_changes(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    first = client.get("/api/v1/chtc")
    etag = first.headers["etag"]
    again = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert again.content == b""
    clock.advance(10)
    push_noisy_sample(service, rng=np.random.default_rng(1))
    changed = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert changed.status_code == 200
    assert changed.headers["etag"] != etag


def test_chtc_goes_stale_without_samples(client: TestClient, clock: ManualClock) -> None:
    etag = client.get("/api/v1/chtc").headers["etag"]
    clock.advance(61)
    r = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert r.status_code == 200
    assert r.json()["status"] == "stale"


def test_chtc_is_identifying_after_a_condition_change(client: TestClient, service: InMemoryService) -> None:
    service.set_condition(5000.0, 15.0, 22.0, state="changing")
    assert client.get("/api/v1/chtc").json()["status"] == "identifying"


def test_chtc_before_any_identification_is_503_no_data(clock: ManualClock) -> None:
    svc = InMemoryService(clock=clock)
    with TestClient(create_app(Settings(), svc, clock=clock)) as c:
        r = c.get("/api/v1/chtc")
    assert r.status_code == 503
    assert r.json()["error"]["code"] == "no_data"
    assert r.headers["retry-after"]


def test_field_mesh_matches_the_service_field(client: TestClient, service: InMemoryService) -> None:
    body = client.get("/api/v1/temperature-field", params={"format": "mesh", "at": "now"}).json()
    f = service.field("now")
    assert body["format"] == "mesh"
    assert body["temperature_unit"] == "°C"
    assert body["length_unit"] == "m"
    assert len(body["nodes_r_m"]) == len(f.nodes_rz) == len(body["temps_c"])
    assert body["triangles"] == f.triangles.tolist()
    np.testing.assert_allclose(body["temps_c"], f.temps_c, atol=1e-4)
    assert body["t_max_c"] == pytest.approx(f.temps_c.max(), abs=1e-4)


def test_field_steady_differs_from_now(client: TestClient) -> None:
    now = client.get("/api/v1/temperature-field", params={"at": "now"}).json()
    steady = client.get("/api/v1/temperature-field", params={"at": "steady"}).json()
    assert steady["at"] == "steady"
    assert steady["t_max_c"] > now["t_max_c"]


def test_field_points_at_nodes_equal_nodal_values(client: TestClient, service: InMemoryService) -> None:
    f = service.field("now")
    idx = [0, len(f.nodes_rz) // 2, len(f.nodes_rz) - 1]
    pts = ";".join(f"{float(f.nodes_rz[i, 0])!r},{float(f.nodes_rz[i, 1])!r}" for i in idx) + ";1.0,1.0"
    body = client.get("/api/v1/temperature-field", params={"format": "points", "points": pts}).json()
    temps = [p["temp_c"] for p in body["points"]]
    np.testing.assert_allclose(temps[:3], f.temps_c[idx], atol=1e-3)
    assert temps[3] is None
    assert [p["inside"] for p in body["points"]] == [True, True, True, False]


def test_field_grid_has_requested_shape_and_nulls_outside(
    client: TestClient, service: InMemoryService
) -> None:
    body = client.get("/api/v1/temperature-field", params={"format": "grid", "nr": 12, "nz": 30}).json()
    assert len(body["r_m"]) == 12 and len(body["z_m"]) == 30
    assert len(body["temps_c"]) == 12 and all(len(row) == 30 for row in body["temps_c"])
    r0, _, _, z1 = service.field("now").bounds_rz
    assert body["r_m"][0] == pytest.approx(r0) and body["z_m"][-1] == pytest.approx(z1)
    # the outer-radius corner at z = z0 is outside the synthetic section (housing starts at z = 0.04 m)
    assert body["temps_c"][-1][0] is None
    assert body["temps_c"][0][0] is not None


def test_sensors_have_residual_and_honour_channel_filter(
    client: TestClient, service: InMemoryService
) -> None:
    body = client.get("/api/v1/sensors").json()
    assert len(body["channels"]) == 32
    for ch in body["channels"]:
        assert ch["residual_c"] == pytest.approx(ch["measured_c"] - ch["predicted_c"], abs=2e-4)
    picked = client.get("/api/v1/sensors", params={"channels": "3,17"}).json()["channels"]
    assert [c["channel"] for c in picked] == [3, 17]


def test_sensors_mask_bad_channels(client: TestClient, service: InMemoryService) -> None:
    temps = np.full(32, 30.0)
    quality = ["ok"] * 32
    quality[4] = "open_circuit"
    service.add_sample(temps, quality=quality)
    ch5 = client.get("/api/v1/sensors", params={"channels": "5"}).json()["channels"][0]
    assert ch5["quality"] == "open_circuit"
    assert ch5["measured_c"] is None and ch5["residual_c"] is None


def test_condition_current_and_recent(client: TestClient) -> None:
    body = client.get("/api/v1/condition").json()
    assert body["current"]["speed_rpm"] == 4000.0
    assert [c["id"] for c in body["recent"]] == [2, 1]
    assert body["current"]["since"].endswith("Z")


def test_identifications_list_paginates_and_filters(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    clock.advance(600)
    service.add_identification([50.0] * 7)
    page = client.get("/api/v1/identifications", params={"limit": 2}).json()
    assert page["total"] == 3
    assert [i["id"] for i in page["items"]] == [3, 2]
    assert page["next_offset"] == 2
    last = client.get("/api/v1/identifications", params={"limit": 2, "offset": 2}).json()
    assert [i["id"] for i in last["items"]] == [1] and last["next_offset"] is None
    since = (clock() - __import__("datetime").timedelta(seconds=60)).isoformat()
    recent = client.get("/api/v1/identifications", params={"since": since}).json()
    assert [i["id"] for i in recent["items"]] == [3]
    older = client.get("/api/v1/identifications", params={"until": since}).json()
    assert [i["id"] for i in older["items"]] == [2, 1]


def test_identification_by_id(client: TestClient) -> None:
    body = client.get("/api/v1/identifications/1").json()
    assert body["id"] == 1
    assert body["condition"]["speed_rpm"] == 3000.0
    assert body["unit"] == "W/(m²·K)"
    assert body["zones"][0]["h_w_m2k"] == pytest.approx(88.21)


def test_healthz_lists_devices_and_degrades(client: TestClient, service: InMemoryService) -> None:
    body = client.get("/api/v1/healthz").json()
    assert body["status"] == "ok"
    assert {d["name"] for d in body["devices"]} == {"modbus", "can", "db"}
    service.set_device("modbus", "down", message="connection refused")
    r = client.get("/api/v1/healthz")
    assert r.status_code == 200
    assert r.json()["status"] == "degraded"


def test_readyz_ready_then_503_when_data_old_or_model_missing(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    assert client.get("/api/v1/readyz").json()["ready"] is True
    clock.advance(120)
    r = client.get("/api/v1/readyz")
    assert r.status_code == 503
    assert r.json()["error"]["code"] == "not_ready"
    assert "old" in r.json()["error"]["message"]
    push_noisy_sample(service, rng=np.random.default_rng(2))
    service.set_model_loaded(False)
    r = client.get("/api/v1/readyz")
    assert r.status_code == 503 and "model not loaded" in r.json()["error"]["message"]


def test_chtc_body_equals_the_schema_serialisation(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    from api.schemas import ChtcOut, chtc_out

    for step in (0.0, 2.25):  # second time from the per-ETag cache
        clock.advance(step)
        r = client.get("/api/v1/chtc")
        snap = service.chtc()
        assert snap is not None
        assert r.json() == json.loads(chtc_out(snap, clock()).model_dump_json())
        ChtcOut.model_validate_json(r.content)
