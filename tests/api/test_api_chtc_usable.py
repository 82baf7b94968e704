"""GET /chtc: one `usable_for_compensation` flag with the reason when false, and `at_bound` per zone
(issue 12, item 17), by the real service's rules (``service.serve.policy.chtc_verdict``)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from drivers.quality import Quality
from service.settings import Settings
from simulator.served import DEMO_FED, Served, feed, served_service
from tests.api.conftest import LENIENT_IDENTIFICATION, sqlite_url
from tests.modes import PER_CONDITION


@pytest.fixture
def lenient(tmp_path: Path) -> Iterator[tuple[Served, TestClient]]:
    """The demo plan with a CI threshold under which the newest identification has every H identified."""
    settings = Settings(identification={**LENIENT_IDENTIFICATION, **PER_CONDITION})
    with (
        served_service(database_url=sqlite_url(tmp_path), settings=settings, feed_samples=DEMO_FED) as s,
        TestClient(create_app(settings, s.service, clock=s.clock)) as c,
    ):
        yield s, c


def test_not_usable_while_an_h_is_not_identified(client: TestClient) -> None:
    body = client.get("/api/v1/chtc").json()
    # ten minutes from a cold start: every 95 % CI is wider than the default threshold
    assert body["status"] == "fresh" and body["usable_for_compensation"] is False
    assert body["reason"].startswith("not_identified: H1, H2, H3, H4, H5, H6, H7")
    assert all(z["at_bound"] is False for z in body["zones"])


def test_usable_only_when_fresh_and_every_h_identified(lenient: tuple[Served, TestClient]) -> None:
    served, client = lenient
    body = client.get("/api/v1/chtc").json()
    assert all(z["identified"] for z in body["zones"])
    assert body["status"] == "fresh" and body["usable_for_compensation"] is True and body["reason"] is None
    served.clock.advance(120.0)  # no new data for 2 min
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "stale" and body["usable_for_compensation"] is False
    # every kind of data stopped: the codes only (the ages are in /readyz, so the snapshot stays put)
    assert body["reason"] == "stale: no_sample, daq_no_good_data, can_no_good_data (see /readyz)"
    assert body["reason_code"] == "stale" and body["action"]


def test_samples_without_enough_good_channels_do_not_keep_it_fresh(
    client: TestClient, served: Served
) -> None:
    """Samples keep arriving, but with 9 channels open only 23 are usable (< 24): the data go stale."""
    for s in served.samples[served.fed : served.fed + 7]:
        quality = s.quality.copy()
        quality[:9] = Quality.OPEN_CIRCUIT
        feed(served, replace(s, quality=quality))
    body = client.get("/api/v1/chtc").json()
    assert body["status"] == "stale" and body["usable_for_compensation"] is False
    assert body["reason"].startswith("stale: daq_no_good_data")
    r = client.get("/api/v1/readyz")
    assert r.status_code == 503 and "daq_no_good_data" in r.json()["error"]["message"]
