"""Probe readings through the API on the real service (``simulator.served``, real SQLite): ``POST
/compensation/measurements`` needs the write token and names a bad field; a reading that agrees is absorbed
and the served mechanical CI tightens; one far off is flagged, stored with accepted=false and not absorbed;
GET lists both; a restart replays the accepted one onto the restored commissioning."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy import select

from api.app import create_app
from service.contracts.mechanics import MechanicsCalibration
from service.estimate.probe import prior_covariance
from service.settings import Settings
from service.store.models import ProbeMeasurementRow
from simulator.served import served_service
from tests.modes import per_condition

from .conftest import DEMO_WINDOWS, WRITE_TOKEN, sqlite_url

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}
MEAS = "/api/v1/compensation/measurements"
COMP = "/api/v1/compensation"


def _settings() -> Settings:
    return per_condition(Settings(api={"token": WRITE_TOKEN}, identification=DEMO_WINDOWS))  # type: ignore[arg-type]


def test_readings_need_the_token_name_bad_fields_tighten_flag_and_survive_a_restart(tmp_path: Path) -> None:
    settings = _settings()
    url = sqlite_url(tmp_path, "probe.db")
    with (
        served_service(database_url=url, settings=settings, feed_samples=40) as s,
        TestClient(create_app(settings, s.service, clock=s.clock)) as c,
    ):
        assert c.post("/api/v1/compensation/reference", headers=AUTH, json={"temperature_c": 21.0}).is_success
        # a commissioning with a wide posterior (the prior's): the readings have room to tighten it
        cov = prior_covariance()
        s.service.set_mechanics(
            MechanicsCalibration(
                x=(0.5, 1.0, 1.0),
                cov=tuple(tuple(float(v) for v in r) for r in cov),
                at=s.clock() - timedelta(hours=1),
                set_by="test",
                source="cli",
                explained=True,
            )
        )
        before = c.get(COMP).json()
        assert before["axial"]["std_mech_um"] > 0.0
        now = s.clock()
        good = {"at": now.isoformat(), "axial_um": before["axial"]["um"] + 0.3, "sd_um": 0.5}
        assert c.post(MEAS, json=good).status_code == 401
        assert c.post(MEAS, headers={"Authorization": "Bearer " + "w" * 40}, json=good).status_code == 403
        for bad, field in (
            ({**good, "at": (now + timedelta(minutes=5)).isoformat()}, "at"),  # in the future
            ({**good, "at": (now - timedelta(hours=5)).isoformat()}, "at"),  # older than the kept history
            ({**good, "at": "2026-11-22T08:06:30+01:00"}, "at"),  # not UTC
            ({**good, "sd_um": 0.0}, "sd_um"),
            ({k: v for k, v in good.items() if k != "axial_um"}, "axial_um"),
            ({**good, "axial_um": "x"}, "axial_um"),
        ):
            r = c.post(MEAS, headers=AUTH, json=bad)
            assert r.status_code == 422, (bad, r.text)
            assert field in r.json()["error"]["message"], r.text
        assert c.get(MEAS).json() == []  # nothing refused is kept
        r = c.post(MEAS, headers=AUTH, json=good)
        assert r.status_code == 200, r.text
        ok = r.json()
        assert ok["accepted"] and ok["mechanics"]["probe_readings_absorbed"] == 1
        # the prediction is the served growth at that instant (the feature row is the served operator's)
        assert abs(ok["predicted_um"] - before["axial"]["um"]) < 0.01, (ok, before["axial"])
        assert ok["sigma_um"] ** 2 > before["axial"]["std_mech_um"] ** 2 + 0.5**2
        after = c.get(COMP).json()
        # one reading measures the fixture offset as well as the mechanics: it moves the served growth to the
        # reading, and the mechanics with the offset are known to within the reading's own 1σ (its sd and the
        # field's part), not better: the offset's 1σ joins the axial mechanical part
        assert before["fixture_offset"] is None
        off = after["fixture_offset"]
        assert off is not None and off["readings"] == 1 and off["steps"] == 0
        assert 0.0 < off["sd_um"] < 5.0 and off["ci95_um"][0] < off["um"] < off["ci95_um"][1]
        cs = settings.compensation  # S = h Σ_θ hᵀ + Var(b) (its prior and 1 h of random walk) + the reading's
        var_b = cs.probe_offset_sd_um**2 + cs.probe_offset_q_um2_per_h * 1.0
        reading_sd = (ok["sigma_um"] ** 2 - var_b - before["axial"]["std_mech_um"] ** 2) ** 0.5
        assert after["axial"]["std_mech_um"] <= reading_sd + 1e-3, (after["axial"], reading_sd)
        assert abs(after["axial"]["um"] - good["axial_um"]) < abs(before["axial"]["um"] - good["axial_um"])
        x_after = [p["value"] for p in after["mechanics"]["parameters"]]
        far = {**good, "axial_um": good["axial_um"] + 200.0, "set_by": "plc"}  # a crash in between
        r = c.post(MEAS, headers=AUTH, json=far)
        assert r.status_code == 200, r.text
        flagged = r.json()
        assert not flagged["accepted"] and flagged["sigma_ratio"] > 3.0
        assert (
            "NOT absorbed" in flagged["message"] and f"{flagged['innovation_um']:+.2f}" in flagged["message"]
        )
        assert [p["value"] for p in flagged["mechanics"]["parameters"]] == x_after  # not absorbed
        listed = c.get(MEAS).json()
        assert [m["accepted"] for m in listed] == [False, True]  # newest first
    with served_service(database_url=url, settings=settings, feed_samples=40) as s:  # a restart
        cal = s.service.compensation_mechanics()
        assert cal is not None and cal.report.get("probe_readings_absorbed") == 1
        assert np.allclose(cal.x, x_after, rtol=0, atol=1e-6)
        m = s.service.compensation_measurements()
        assert [q.accepted for q in m] == [False, True] and all(q.id is not None for q in m)
        with s.persistence.session_factory() as session:
            rows = session.scalars(select(ProbeMeasurementRow).order_by(ProbeMeasurementRow.id)).all()
            assert [r.accepted for r in rows] == [True, False] and rows[1].set_by == "plc"
        with TestClient(create_app(settings, s.service, clock=s.clock)) as c:
            assert c.post(
                "/api/v1/compensation/reference", headers=AUTH, json={"temperature_c": 21.0}
            ).is_success
            comp = c.get(COMP).json()
            assert comp["mechanics"]["probe_readings_absorbed"] == 1
            assert comp["axial"]["std_mech_um"] > 0.0


def test_without_a_commissioning_readings_start_from_the_prior_and_do_not_make_it_usable(
    tmp_path: Path,
) -> None:
    settings = per_condition(
        Settings(
            api={"token": WRITE_TOKEN},  # type: ignore[arg-type]
            identification=DEMO_WINDOWS,  # type: ignore[arg-type]
            compensation={"require_mechanics_calibration": True},  # type: ignore[arg-type]
        )
    )
    with (
        served_service(
            database_url=sqlite_url(tmp_path, "prior.db"), settings=settings, feed_samples=40
        ) as s,
        TestClient(create_app(settings, s.service, clock=s.clock)) as c,
    ):
        reading = {"at": s.clock().isoformat(), "axial_um": 2.0, "sd_um": 1.0}
        r = c.post(MEAS, headers=AUTH, json=reading)
        assert r.status_code == 422 and "reference" in r.json()["error"]["message"], r.text  # no zero yet
        assert c.post("/api/v1/compensation/reference", headers=AUTH, json={"temperature_c": 21.0}).is_success
        assert c.get("/api/v1/compensation/mechanics").status_code == 404
        r = c.post(MEAS, headers=AUTH, json=reading)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["accepted"] and body["mechanics"]["source"] == "prior"
        sd = {p["name"]: p["sd"] for p in body["mechanics"]["parameters"]}
        # from the prior (restraint 1σ 1/√12, α 5 %): never wider after a reading
        assert sd["restraint"] <= 0.2887 + 1e-4 and sd["alpha_shaft"] <= 0.05 + 1e-6
        comp = c.get(COMP).json()
        assert comp["mechanics"]["source"] == "prior" and comp["axial"]["std_mech_um"] > 0.0
        assert comp["reason_code"] == "mechanics_uncalibrated"  # readings alone are not a commissioning
