"""GET /api/v1/chtc/map (issue 17): the H map over the speed range, its bands and the visited speeds.

The body builder is checked on a real map fit (``model.hmap_identify.identify_map`` of 30 min of a seeded
virtual-plant duty cycle: finer mesh, its own h_true); the endpoint on the real service, in per-condition
mode (404 naming the setting) and in speed-map mode (the body is the service's snapshot, ETag/304, 503 before
the first fit).
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.schemas import chtc_map_out
from model import hmap_identify as hi
from model.hmap import NODES
from model.plant import VirtualPlant
from service.contracts.snapshots import H_UNIT, ZONE_NAMES, ChtcMapSnapshot
from service.identify.speedmap import MAP_GRID_RPM, SpeedMap
from service.serve.policy import map_verdict
from service.serve.views import chtc_map_snapshot
from service.settings import Settings
from simulator.served import Served
from tests.api.conftest import served_map_mode
from tests.model_hmap.duty import DutyRun, load_service_model, run_duty, window

T_END = datetime(2026, 11, 22, 8, 0, tzinfo=UTC)
CI_THRESHOLD = 0.5  # identification.ci_rel_threshold's default


@pytest.fixture(scope="module")
def duty() -> DutyRun:
    """30 min of a seeded duty cycle (speed changes every 1-6 min), sampled every 10 s."""
    return run_duty(VirtualPlant(load_service_model().spec, seed=3), 3, duration_s=1800.0)


@pytest.fixture(scope="module")
def fitted(duty: DutyRun) -> SpeedMap:
    """The map fitted to the whole 30 min from the cold prior, as the service keeps it."""
    m = load_service_model()
    w = window(m.spec, duty.run, 0, 180, float(duty.run.ambient_c[0]))
    fit = hi.identify_map(m.rom, w, NODES.prior(m.spec))
    return SpeedMap(
        family="nodes",
        mean=fit.posterior.mean,
        cov=fit.posterior.cov,
        visited_rpm=fit.visited_rpm,
        visited_s=fit.visited_s,
        fitted_at=T_END,
        identification_id=4,
        rmse_c=fit.rmse_c,
    )


def _snapshot(m: SpeedMap, speed_rpm: float, ambient_c: float = 22.3) -> ChtcMapSnapshot:
    newest = T_END + timedelta(seconds=60)
    fresh = map_verdict(
        m,
        newest_t=newest,
        speed_rpm=speed_rpm,
        problems=(),
        converging_since=None,
        fresh_s=900.0,
        margin_rpm=300.0,
        min_visit_s=60.0,
    )
    return chtc_map_snapshot(
        m,
        ambient_c=ambient_c,
        verdict=fresh,
        newest_sample_at=newest,
        current_speed_rpm=speed_rpm,
        ci_threshold=CI_THRESHOLD,
        margin_rpm=300.0,
    )


@pytest.mark.slow
def test_the_body_carries_the_fitted_map_with_units_bands_and_visited_speeds(
    fitted: SpeedMap, duty: DutyRun
) -> None:
    speed = float(duty.run.speed_rpm[179])  # the window's last speed: visited
    snap = _snapshot(fitted, speed)
    now = T_END + timedelta(seconds=65)
    body = chtc_map_out(snap, now, spindle_id="s1").model_dump(mode="json")
    assert body["status"] == "fresh" and body["reason"] is None
    assert body["unit"] == H_UNIT == "W/(m²·K)"
    assert body["family"] == "nodes" and body["identification_id"] == 4
    assert body["fitted_at"] == "2026-11-22T08:00:00Z" and body["served_at"] == "2026-11-22T08:01:05Z"
    assert body["sample_age_s"] == 5.0 and body["current_speed_rpm"] == speed
    assert body["ambient_c"] == 22.3 and body["rmse_c"] == pytest.approx(fitted.rmse_c, abs=5e-5)
    assert body["speeds_rpm"] == list(MAP_GRID_RPM) and body["speeds_rpm"][-1] == 7000.0
    assert [z["name"] for z in body["zones"]] == list(ZONE_NAMES)
    for i, z in enumerate(body["zones"]):
        h, lo, hi_ = (np.array(z[k], dtype=float) for k in ("h_w_m2k", "ci95_lo_w_m2k", "ci95_hi_w_m2k"))
        # the snapshot's numbers (0.1 mW/(m²·K) rounding), each band positive and around H
        np.testing.assert_allclose(h, snap.h_w_m2k[:, i], atol=5e-5, rtol=0)
        np.testing.assert_allclose(lo, snap.ci95_lo_w_m2k[:, i], atol=5e-5, rtol=0)
        np.testing.assert_allclose(hi_, snap.ci95_hi_w_m2k[:, i], atol=5e-5, rtol=0)
        assert np.all(lo > 0) and np.all(lo <= h) and np.all(h <= hi_), z["name"]
        # identified: the band's half-width in ln H within the threshold, recomputed from the served numbers
        half = 0.5 * np.log(hi_ / lo)
        ok = np.abs(half - CI_THRESHOLD) > 1e-3  # off the threshold by more than the rounding
        assert np.array_equal(np.array(z["identified"])[ok], (half <= CI_THRESHOLD)[ok]), z["name"]
    # the map's H at a grid speed is the fit's own evaluation there
    k = int(np.flatnonzero(MAP_GRID_RPM == 3500.0)[0])
    h35, _, _ = fitted.h_at([3500.0], 22.3)
    np.testing.assert_allclose([z["h_w_m2k"][k] for z in body["zones"]], h35[0], atol=5e-5, rtol=0)
    # the visited speeds are the window's speeds, with 10 s per sample step
    seen = np.unique(duty.run.speed_rpm[:180])
    assert [v["speed_rpm"] for v in body["visited"]] == list(seen)
    steps = [10.0 * np.count_nonzero(duty.run.speed_rpm[:180] == s) for s in seen]
    assert [v["duration_s"] for v in body["visited"]] == steps
    assert sum(steps) == 1800.0


@pytest.mark.slow
def test_the_bands_are_narrow_where_the_data_were_and_wide_where_they_were_not(fitted: SpeedMap) -> None:
    """H7 (the housing, well determined) over the speeds the window visited vs. a speed it never reached:
    the served band says where the map is the prior's interpolation."""
    body = chtc_map_out(_snapshot(fitted, 0.0), T_END, spindle_id="s1").model_dump(mode="json")
    grid = np.array(body["speeds_rpm"])
    h7 = body["zones"][6]
    width = np.log(np.array(h7["ci95_hi_w_m2k"]) / np.array(h7["ci95_lo_w_m2k"]))
    visited = [v["speed_rpm"] for v in body["visited"] if v["duration_s"] >= 120.0]
    far = [s for s in grid if min(abs(s - v) for v in fitted.visited_rpm) >= 1000.0]
    assert far, "the window visited every speed"
    near_w = width[np.isin(grid, visited)]
    far_w = width[np.isin(grid, far)]
    assert near_w.max() < far_w.min(), (near_w, far_w)


@pytest.mark.slow
def test_an_unvisited_current_speed_is_identifying_with_the_reason(fitted: SpeedMap) -> None:
    unvisited = next(s for s in MAP_GRID_RPM if min(abs(s - fitted.visited_rpm)) > 300.0)
    body = chtc_map_out(_snapshot(fitted, float(unvisited)), T_END, spindle_id="s1").model_dump(mode="json")
    assert body["status"] == "identifying" and body["reason_code"] == "speed_not_visited"
    assert body["reason"].startswith(f"speed_not_visited: {unvisited:.0f} rpm is not within 300 rpm")


def test_per_condition_mode_answers_404_naming_the_setting(ro_client: TestClient) -> None:
    assert ro_client.app.state.service.identification_mode() == "per_condition"  # type: ignore[attr-defined]
    r = ro_client.get("/api/v1/chtc/map")
    assert r.status_code == 404
    err = r.json()["error"]
    assert err["code"] == "not_found"
    assert "identification.mode is per_condition" in err["message"]
    assert 'identification.mode = "speed_map"' in err["message"]
    assert "etag" not in r.headers


def test_the_openapi_document_describes_the_map(ro_client: TestClient) -> None:
    doc: dict[str, Any] = ro_client.get("/api/v1/openapi.json").json()
    op = doc["paths"]["/api/v1/chtc/map"]["get"]
    assert op["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/ChtcMapOut")
    assert {"304", "404", "414", "503"} <= set(op["responses"])
    assert "per-condition" in op["responses"]["404"]["description"]
    assert "Retry-After" in op["responses"]["503"]["headers"]
    out = doc["components"]["schemas"]["ChtcMapOut"]["properties"]
    for name in ("speeds_rpm", "zones", "visited", "fitted_at", "ambient_c", "unit", "status", "served_at"):
        assert name in out, name
    zone = doc["components"]["schemas"]["MapZoneOut"]["properties"]
    assert {"h_w_m2k", "ci95_lo_w_m2k", "ci95_hi_w_m2k", "identified"} <= set(zone)
    assert set(doc["components"]["schemas"]["VisitedOut"]["properties"]) == {"speed_rpm", "duration_s"}


# --- the endpoint on the real service in speed-map mode (simulator.served, MAP_PLAN)


@pytest.fixture(scope="module")
def map_served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    with served_map_mode(tmp_path_factory.mktemp("map-mode")) as s:
        yield s


@pytest.fixture
def map_client(map_served: Served) -> Iterator[TestClient]:
    with TestClient(create_app(Settings(), map_served.service, clock=map_served.clock)) as c:
        yield c


def test_the_endpoint_serves_the_service_map(map_client: TestClient, map_served: Served) -> None:
    svc = map_served.service
    assert svc.identification_mode() == "speed_map"
    r = map_client.get("/api/v1/chtc/map")
    snap = svc.chtc_map()
    assert r.status_code == 200 and snap is not None, r.text
    body = r.json()
    assert body["status"] == snap.status.value and body["reason"] == snap.reason
    assert body["identification_id"] == snap.identification_id is not None
    assert datetime.fromisoformat(body["fitted_at"]) == snap.fitted_at
    assert datetime.fromisoformat(body["newest_sample_at"]) == snap.newest_sample_at == map_served.clock.now
    assert body["sample_age_s"] == 0.0 and body["unit"] == "W/(m²·K)"
    assert body["speeds_rpm"] == [float(x) for x in snap.speeds_rpm]
    for i, z in enumerate(body["zones"]):
        for key, arr in (
            ("h_w_m2k", snap.h_w_m2k),
            ("ci95_lo_w_m2k", snap.ci95_lo_w_m2k),
            ("ci95_hi_w_m2k", snap.ci95_hi_w_m2k),
        ):
            np.testing.assert_allclose(z[key], arr[:, i], atol=5e-5, rtol=0, err_msg=f"{z['name']} {key}")
        assert z["identified"] == [bool(x) for x in snap.identified[:, i]]
        assert min(z["ci95_lo_w_m2k"]) > 0
    # the visited speeds: the duty cycle's speeds fed before the fit's window ended, in ascending order
    rpm = [v["speed_rpm"] for v in body["visited"]]
    assert rpm == sorted(rpm) == [float(x) for x in snap.visited_rpm]
    fed = {float(x.speed_rpm) for x in map_served.samples[: map_served.fed] if x.t <= snap.fitted_at}
    assert set(rpm) <= fed and len(rpm) >= 4
    assert all(v["duration_s"] > 0 for v in body["visited"])
    # /chtc in speed-map mode: H1-H7 from this map at the current speed (a grid speed of the duty cycle)
    now = map_client.get("/api/v1/chtc").json()
    k = body["speeds_rpm"].index(body["current_speed_rpm"])
    np.testing.assert_allclose(
        [z["h_w_m2k"] for z in now["zones"]], [z["h_w_m2k"][k] for z in body["zones"]], rtol=2e-3
    )
    assert now["status"] == body["status"]


def test_etag_gives_304_until_the_next_sample(map_client: TestClient, map_served: Served) -> None:
    first = map_client.get("/api/v1/chtc/map")
    etag = first.headers["etag"]
    assert etag.startswith('W/"') and first.headers["cache-control"] == "no-cache"
    head = map_client.head("/api/v1/chtc/map")  # the GET's status and headers, no body
    assert head.status_code == 200 and head.headers["etag"] == etag and not head.content
    again = map_client.get("/api/v1/chtc/map", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.headers["etag"] == etag and not again.content
    map_served.clock.advance(3.0)  # served_at moves, the map does not: still 304
    assert map_client.get("/api/v1/chtc/map", headers={"If-None-Match": etag}).status_code == 304
    map_served.feed_next(1)
    after = map_client.get("/api/v1/chtc/map", headers={"If-None-Match": etag})
    assert after.status_code == 200 and after.headers["etag"] != etag
    assert after.json()["newest_sample_at"] != first.json()["newest_sample_at"]


def test_speed_map_mode_before_the_first_fit_answers_503(tmp_path: Path) -> None:
    with served_map_mode(tmp_path, feed_samples=30) as s:  # 5 min at rest: no map fitted yet
        assert s.service.chtc_map() is None
        with TestClient(create_app(Settings(), s.service, clock=s.clock)) as c:
            r = c.get("/api/v1/chtc/map")
    assert r.status_code == 503 and r.headers["retry-after"] == "5"
    assert r.json()["error"]["code"] == "no_data"
    assert "no speed map fitted yet" in r.json()["error"]["message"]


@pytest.mark.slow
def test_after_a_restart_the_stored_map_is_served_as_restored_and_stale(tmp_path: Path) -> None:
    with served_map_mode(tmp_path) as s:
        before = s.service.chtc_map()
        assert before is not None and not before.restored
    # the same database, nothing fed yet since the restart
    with served_map_mode(tmp_path, feed_samples=0) as s2:
        with TestClient(create_app(Settings(), s2.service, clock=s2.clock)) as c:
            body = c.get("/api/v1/chtc/map").json()
        restored = s2.service.chtc_map()
    assert restored is not None
    assert body["restored"] is True and body["status"] == "stale"
    assert body["reason"].startswith("restored:")
    assert body["identification_id"] == before.identification_id
    assert datetime.fromisoformat(body["fitted_at"]) == before.fitted_at
    assert [v["speed_rpm"] for v in body["visited"]] == [float(x) for x in before.visited_rpm]
    assert body["newest_sample_at"] is None and body["current_speed_rpm"] is None
    np.testing.assert_allclose(
        [z["h_w_m2k"] for z in body["zones"]],
        restored.h_w_m2k.T,
        atol=5e-5,
    )
