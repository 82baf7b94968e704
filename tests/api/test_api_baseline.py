"""POST /sensors/baseline (token) and the offsets shown by GET /sensors, from the real calibrator."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.plant import Segment
from service.settings import Settings
from simulator.served import Plan, served_service

from .conftest import WRITE_TOKEN, sqlite_url

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}
AT_REST = Plan(profile=(Segment(420.0, 0.0, 0.0, 22.0),))  # 7 min at rest at the ambient, from equilibrium


def test_baseline_needs_the_token_and_names_why_it_cannot_be_taken(client: TestClient) -> None:
    assert client.post("/api/v1/sensors/baseline").status_code == 401
    r = client.post("/api/v1/sensors/baseline", headers=AUTH)  # the spindle is running
    assert r.status_code == 409 and "no samples at rest" in r.text  # a state conflict, not a 5xx


def test_baseline_at_rest_is_taken_and_shown_by_sensors(tmp_path: Path) -> None:
    with served_service(database_url=sqlite_url(tmp_path), plan=AT_REST) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        with TestClient(app) as c:
            r = c.post("/api/v1/sensors/baseline", headers=AUTH)
            ch = c.get("/api/v1/sensors").json()["channels"]
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["t_to"] == "2026-11-22T07:07:00Z" and body["source"] == "manual"
    assert body["samples"] == 31  # the last 5 min (offset_rest_s) at 10 s, both ends included
    assert len(body["offsets_c"]) == len(body["sd_c"]) == 32
    assert all(abs(x) < 0.3 and 0 < sd < 0.1 for x, sd in zip(body["offsets_c"], body["sd_c"], strict=True))
    assert [c["offset_c"] for c in ch] == pytest.approx(body["offsets_c"], abs=1e-4)
    assert {c["offset_calibrated_at"] for c in ch} == {"2026-11-22T07:07:00Z"}
    assert {c["offset_source"] for c in ch} == {"manual"}


def test_sensors_show_offset_fields(client: TestClient) -> None:
    ch = client.get("/api/v1/sensors").json()["channels"][0]
    assert {"offset_c", "offset_sd_c", "offset_calibrated_at", "offset_source"} <= set(ch)
    assert ch["offset_source"] is None  # no baseline yet


def test_a_commissioning_with_a_baseline_gives_the_offsets_until_a_rest(tmp_path: Path) -> None:
    """A running spindle without a baseline (a restart with an empty database): ``/compensation`` is blocked
    by no_offset_baseline; the commissioning set (its test's rest baseline in its report) gives the offsets,
    shown by GET /sensors with the source ``commissioning``; the block stays, naming the check, until the
    offsets have been checked against the live residuals (``service.core.baselinecheck``, 10 min; the
    check itself: tests/service/test_commission_baseline.py) (issue 40 part 3)."""
    from datetime import timedelta

    import numpy as np

    from service.contracts.calibration import Calibration
    from service.contracts.commissionbaseline import AGE_SD_C, BASELINE_KEY, baseline_entry
    from service.contracts.mechanics import MechanicsCalibration

    settings = Settings(api={"token": WRITE_TOKEN}, compensation={"require_offset_baseline": True})
    with served_service(database_url=sqlite_url(tmp_path), settings=settings, feed_samples=20) as s:
        app = create_app(settings, s.service, clock=s.clock)
        offsets = np.linspace(-0.2, 0.2, 32)
        rest = Calibration(
            offsets_c=offsets,
            sd_c=np.full(32, 0.01),
            t_from=s.clock() - timedelta(days=30, minutes=15),
            t_to=s.clock() - timedelta(days=30),
            samples=91,
            source="auto",
        )
        with TestClient(app) as c:
            before = c.get("/api/v1/compensation").json()
            s.service.set_mechanics(
                MechanicsCalibration(
                    x=(0.6, 1.0, 1.0),
                    cov=((0.01, 0.0, 0.0), (0.0, 0.001, 0.0), (0.0, 0.0, 0.001)),
                    at=s.clock() - timedelta(days=30),
                    set_by="test",
                    source="cli",
                    explained=True,
                    report={BASELINE_KEY: baseline_entry(rest)},
                )
            )
            ch = c.get("/api/v1/sensors").json()["channels"]
            after = c.get("/api/v1/compensation").json()

    def reasons(body: dict) -> set[str]:  # type: ignore[type-arg]
        return {body["reason_code"], *(b["reason_code"] for b in body["blocking"])}

    assert "no_offset_baseline" in reasons(before), before
    assert {c["offset_source"] for c in ch} == {"commissioning"}
    assert [c["offset_c"] for c in ch] == pytest.approx(list(offsets), abs=1e-4)
    assert [c["offset_sd_c"] for c in ch] == pytest.approx([float(np.hypot(0.01, AGE_SD_C))] * 32, abs=1e-4)
    blocking = {b["reason_code"]: b for b in after["blocking"]}
    assert "no_offset_baseline" in blocking, after  # unchecked: not yet a founded baseline
    assert "check" in json.dumps(blocking["no_offset_baseline"]), blocking
