"""Read endpoints against the real service (``tests/api/conftest.py``): values, units, timestamps, ETag,
statuses."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from drivers.quality import Quality
from service.contracts.snapshots import ZONE_NAMES
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import Served, feed, served_service
from tests.api.conftest import ManualClock, sqlite_url


def test_chtc_returns_current_h_with_units_ci_and_provenance(
    ro_client: TestClient, ro_service: SoftSensorService
) -> None:
    r = ro_client.get("/api/v1/chtc")
    assert r.status_code == 200
    body = r.json()
    snap = ro_service.chtc()
    assert snap is not None
    assert body["unit"] == "W/(m²·K)"
    assert [z["name"] for z in body["zones"]] == list(ZONE_NAMES)
    stored = ro_service.get_identification(snap.identification_id)  # the newest, at the current condition
    np.testing.assert_allclose([z["h_w_m2k"] for z in body["zones"]], stored.h, atol=1e-4)
    assert snap.identification_id == 2 and stored.condition.id == ro_service.condition().id == 2
    np.testing.assert_allclose([z["ci95_lo_w_m2k"] for z in body["zones"]], snap.ci95_lo, atol=1e-4)
    np.testing.assert_allclose([z["ci95_hi_w_m2k"] for z in body["zones"]], snap.ci95_hi, atol=1e-4)
    assert [z["identified"] for z in body["zones"]] == snap.identified.tolist()
    assert body["status"] == "fresh"
    assert body["identification_id"] == snap.identification_id
    assert body["condition"]["speed_rpm"] == snap.condition.speed_rpm
    assert body["rmse_c"] == pytest.approx(snap.rmse_c)
    assert body["fit"] == pytest.approx(snap.fit)
    assert body["identified_at"].endswith("Z")
    assert datetime.fromisoformat(body["newest_sample_at"]) == snap.newest_sample_at


def test_chtc_sample_age_follows_the_clock(client: TestClient, clock: ManualClock) -> None:
    clock.advance(3.5)
    assert client.get("/api/v1/chtc").json()["sample_age_s"] == pytest.approx(3.5)


def test_chtc_etag_gives_304_until_something_changes(client: TestClient, served: Served) -> None:
    first = client.get("/api/v1/chtc")
    etag = first.headers["etag"]
    again = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert again.content == b""
    served.feed_next(1)  # the next sample, 10 s later
    changed = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert changed.status_code == 200
    assert changed.headers["etag"] != etag


def test_chtc_goes_stale_without_samples(client: TestClient, clock: ManualClock) -> None:
    etag = client.get("/api/v1/chtc").headers["etag"]
    clock.advance(61)
    r = client.get("/api/v1/chtc", headers={"If-None-Match": etag})
    assert r.status_code == 200
    assert r.json()["status"] == "stale"


def test_chtc_is_identifying_after_a_condition_change(client: TestClient, served: Served) -> None:
    """The speed leaves the condition: the detector holds it as changing until it is confirmed."""
    for s in served.samples[served.fed : served.fed + 3]:
        feed(served, replace(s, speed_rpm=5000.0))
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "identifying" and body["condition"]["id"] == 2
    assert client.get("/api/v1/condition").json()["current"]["state"] == "changing"


def test_chtc_before_any_identification_is_503_no_data(tmp_path: Path) -> None:
    """Five minutes of samples, half the first window: no identification yet."""
    with (
        served_service(database_url=sqlite_url(tmp_path), feed_samples=30) as s,
        TestClient(create_app(Settings(), s.service, clock=s.clock)) as c,
    ):
        r = c.get("/api/v1/chtc")
        assert c.get("/api/v1/sensors").status_code == 200  # the samples are there
    assert r.status_code == 503
    assert r.json()["error"]["code"] == "no_data"
    assert r.headers["retry-after"]


def test_field_mesh_matches_the_service_field(ro_client: TestClient, ro_service: SoftSensorService) -> None:
    body = ro_client.get("/api/v1/temperature-field", params={"format": "mesh", "at": "now"}).json()
    f = ro_service.field("now")
    assert body["format"] == "mesh"
    assert body["temperature_unit"] == "°C"
    assert body["length_unit"] == "m"
    assert len(body["nodes_r_m"]) == len(f.nodes_rz) == len(body["temps_c"])
    assert body["triangles"] == f.triangles.tolist()
    np.testing.assert_allclose(body["temps_c"], f.temps_c, atol=1e-4)
    assert body["t_max_c"] == pytest.approx(f.temps_c.max(), abs=1e-4)


def test_field_steady_differs_from_now(ro_client: TestClient) -> None:
    now = ro_client.get("/api/v1/temperature-field", params={"at": "now"}).json()
    steady = ro_client.get("/api/v1/temperature-field", params={"at": "steady"}).json()
    assert steady["at"] == "steady"
    assert steady["t_max_c"] > now["t_max_c"]


def test_field_points_at_nodes_equal_nodal_values(
    ro_client: TestClient, ro_service: SoftSensorService
) -> None:
    f = ro_service.field("now")
    idx = [0, len(f.nodes_rz) // 2, len(f.nodes_rz) - 1]
    pts = ";".join(f"{float(f.nodes_rz[i, 0])!r},{float(f.nodes_rz[i, 1])!r}" for i in idx) + ";1.0,1.0"
    body = ro_client.get("/api/v1/temperature-field", params={"format": "points", "points": pts}).json()
    temps = [p["temp_c"] for p in body["points"]]
    np.testing.assert_allclose(temps[:3], f.temps_c[idx], atol=1e-3)
    assert temps[3] is None
    assert [p["inside"] for p in body["points"]] == [True, True, True, False]


def test_field_grid_has_requested_shape_and_nulls_outside(
    ro_client: TestClient, ro_service: SoftSensorService
) -> None:
    body = ro_client.get("/api/v1/temperature-field", params={"format": "grid", "nr": 12, "nz": 30}).json()
    assert len(body["r_m"]) == 12 and len(body["z_m"]) == 30
    assert len(body["temps_c"]) == 12 and all(len(row) == 30 for row in body["temps_c"])
    f = ro_service.field("now")
    r0, _, _, z1 = f.bounds_rz
    assert body["r_m"][0] == pytest.approx(r0) and body["z_m"][-1] == pytest.approx(z1)
    # null exactly where the grid point lies outside the section (the spindle is not a rectangle)
    rr, zz = np.meshgrid(body["r_m"], body["z_m"], indexing="ij")
    outside = np.isnan(f.evaluate(np.c_[rr.ravel(), zz.ravel()])).reshape(rr.shape)
    assert outside.any() and not outside.all()
    assert [[t is None for t in row] for row in body["temps_c"]] == outside.tolist()


def test_sensors_have_residual_and_honour_channel_filter(ro_client: TestClient) -> None:
    body = ro_client.get("/api/v1/sensors").json()
    assert len(body["channels"]) == 32
    for ch in body["channels"]:
        assert ch["residual_c"] == pytest.approx(ch["measured_c"] - ch["predicted_c"], abs=2e-4)
    picked = ro_client.get("/api/v1/sensors", params={"channels": "3,17"}).json()["channels"]
    assert [c["channel"] for c in picked] == [3, 17]


def test_sensors_mask_bad_channels(client: TestClient, served: Served) -> None:
    s = served.samples[served.fed]
    quality = s.quality.copy()
    quality[4] = Quality.OPEN_CIRCUIT
    feed(served, replace(s, quality=quality))
    ch5 = client.get("/api/v1/sensors", params={"channels": "5"}).json()["channels"][0]
    assert ch5["quality"] == "open_circuit"
    assert ch5["measured_c"] is None and ch5["residual_c"] is None


def test_condition_current_and_recent(ro_client: TestClient) -> None:
    body = ro_client.get("/api/v1/condition").json()
    assert body["current"]["speed_rpm"] == 4000.0
    assert [c["id"] for c in body["recent"]] == [2, 1]
    assert body["current"]["since"].endswith("Z")


def test_identifications_list_paginates_and_filters(
    client: TestClient, served: Served, clock: ManualClock
) -> None:
    served.feed_next(30)  # 5 min more, then an identification asked for now
    served.service.request_identification("operator check")
    served.settle()
    page = client.get("/api/v1/identifications", params={"limit": 2}).json()
    assert page["total"] == 3
    assert [i["id"] for i in page["items"]] == [3, 2]
    assert page["next_offset"] == 2
    last = client.get("/api/v1/identifications", params={"limit": 2, "offset": 2}).json()
    assert [i["id"] for i in last["items"]] == [1] and last["next_offset"] is None
    since = (clock() - timedelta(seconds=60)).isoformat()
    recent = client.get("/api/v1/identifications", params={"since": since}).json()
    assert [i["id"] for i in recent["items"]] == [3]
    older = client.get("/api/v1/identifications", params={"until": since}).json()
    assert [i["id"] for i in older["items"]] == [2, 1]


def test_identification_by_id(ro_client: TestClient, ro_service: SoftSensorService) -> None:
    body = ro_client.get("/api/v1/identifications/1").json()
    assert body["id"] == 1
    assert body["condition"]["speed_rpm"] == 3000.0
    assert body["unit"] == "W/(m²·K)"
    h1 = ro_service.get_identification(1).h[0]
    assert body["zones"][0]["h_w_m2k"] == pytest.approx(h1, abs=1e-4)


@pytest.mark.slow  # over ~5 s alone (issue 25: the fast subset under 5 min)
def test_healthz_lists_devices_and_degrades(client: TestClient, served_db_down: Served) -> None:
    body = client.get("/api/v1/healthz").json()
    assert body["status"] == "ok" and body["model_loaded"] is True
    assert {d["name"]: d["status"] for d in body["devices"]} == {"db": "ok", "worker": "ok", "filter": "ok"}
    s = served_db_down
    with TestClient(create_app(Settings(), s.service, clock=s.clock)) as down:
        r = down.get("/api/v1/healthz")
    assert r.status_code == 200
    assert r.json()["status"] == "degraded"
    (db,) = [d for d in r.json()["devices"] if d["name"] == "db"]
    assert db["status"] == "down" and db["message"].startswith("buffering")


def test_readyz_ready_then_503_when_data_old(client: TestClient, served: Served, clock: ManualClock) -> None:
    assert client.get("/api/v1/readyz").json()["ready"] is True
    clock.advance(120)
    r = client.get("/api/v1/readyz")
    assert r.status_code == 503
    assert r.json()["error"]["code"] == "not_ready"
    assert "old" in r.json()["error"]["message"]
    served.feed_next(1)  # clock - 120 s + 10 s: still old
    assert client.get("/api/v1/readyz").status_code == 503


def test_readyz_503_while_the_model_loads(tmp_path: Path) -> None:
    with (
        served_service(database_url=sqlite_url(tmp_path), loading=True) as s,
        TestClient(create_app(Settings(), s.service, clock=s.clock)) as c,
    ):
        r = c.get("/api/v1/readyz")
        assert r.status_code == 503 and "model not loaded" in r.json()["error"]["message"]
        assert c.get("/api/v1/healthz").json()["model_loaded"] is False
        s.started()
        s.feed_next(1)
        assert c.get("/api/v1/readyz").status_code == 200


def test_chtc_body_equals_the_schema_serialisation(
    client: TestClient, service: SoftSensorService, clock: ManualClock
) -> None:
    from api.schemas import ChtcOut, chtc_out

    for step in (0.0, 2.25):  # second time from the per-ETag cache
        clock.advance(step)
        r = client.get("/api/v1/chtc")
        snap = service.chtc()
        assert snap is not None
        out = chtc_out(snap, clock(), spindle_id=Settings().spindle.id)
        assert r.json() == json.loads(out.model_dump_json())
        ChtcOut.model_validate_json(r.content)
