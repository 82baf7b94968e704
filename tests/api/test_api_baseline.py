"""POST /sensors/baseline (token) and the offsets shown by GET /sensors, from the real calibrator."""

from __future__ import annotations

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
