"""POST /sensors/baseline (token) and the offsets shown by GET /sensors."""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi.testclient import TestClient

from service.serve.interface import OffsetBaseline
from service.serve.interface_memory import InMemoryService

from .conftest import WRITE_TOKEN

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}


def test_baseline_needs_the_token_and_names_why_it_cannot_be_taken(
    client: TestClient, service: InMemoryService
) -> None:
    assert client.post("/api/v1/sensors/baseline").status_code == 401
    r = client.post("/api/v1/sensors/baseline", headers=AUTH)
    assert r.status_code == 409 and "no samples at rest" in r.text  # a state conflict, not a 5xx
    t0, t1 = datetime(2026, 11, 22, 6, 0, tzinfo=UTC), datetime(2026, 11, 22, 6, 30, tzinfo=UTC)
    service.baseline = OffsetBaseline(t0, t1, "manual", 181, (0.12345678,) + (None,) * 31, (0.011,) * 32)
    r = client.post("/api/v1/sensors/baseline", headers=AUTH)
    assert r.status_code == 200
    body = r.json()
    assert body["t_to"] == "2026-11-22T06:30:00Z" and body["source"] == "manual" and body["samples"] == 181
    assert body["offsets_c"][0] == 0.1235 and body["offsets_c"][1] is None and body["sd_c"][5] == 0.011
    ch = client.get("/api/v1/sensors").json()["channels"]  # the baseline now in use, per channel
    assert ch[0]["offset_c"] == 0.1235 and ch[0]["offset_source"] == "manual" and ch[1]["offset_c"] is None
    assert ch[0]["offset_calibrated_at"] == "2026-11-22T06:30:00Z" and ch[5]["offset_sd_c"] == 0.011


def test_sensors_show_offset_fields(client: TestClient) -> None:
    ch = client.get("/api/v1/sensors").json()["channels"][0]
    assert {"offset_c", "offset_sd_c", "offset_calibrated_at", "offset_source"} <= set(ch)
    assert ch["offset_source"] is None  # no baseline yet
