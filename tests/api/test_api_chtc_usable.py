"""GET /chtc: one `usable_for_compensation` flag with the reason when false, and `at_bound` per zone
(issue 12, item 17)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.serve.interface_memory import PAPER_H_4000, InMemoryService
from tests.api.conftest import ManualClock


def test_usable_only_when_fresh_and_every_h_identified(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    body = client.get("/api/v1/chtc").json()
    # the demo's newest identification leaves H1 and H4 unidentified
    assert body["usable_for_compensation"] is False
    assert body["reason"].startswith("not_identified: H1, H4")
    assert all(z["at_bound"] is False for z in body["zones"])
    service.add_identification(PAPER_H_4000)
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "fresh" and body["usable_for_compensation"] is True and body["reason"] is None
    clock.advance(120.0)  # no new good data for 2 min
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "stale" and body["usable_for_compensation"] is False
    assert body["reason"].startswith("stale: daq_no_good_data")


def test_samples_without_enough_good_channels_do_not_keep_it_fresh(
    client: TestClient, service: InMemoryService, clock: ManualClock
) -> None:
    """Samples keep arriving, but with 9 channels open only 23 are usable (< 24): the data go stale."""
    service.add_identification(PAPER_H_4000)
    temps = service.predicted_at_sensors()
    for _ in range(7):
        clock.advance(10.0)
        service.add_sample(temps, quality=["open_circuit"] * 9 + ["ok"] * 23)
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "stale" and body["usable_for_compensation"] is False
    r = client.get("/api/v1/readyz")
    assert r.status_code == 503 and "daq_no_good_data" in r.json()["error"]["message"]
