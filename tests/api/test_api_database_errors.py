"""Database failures reach the client as the error shape or a marked partial page, never a bare 500.

The real service (``simulator.served``) on a SQLite database that cannot be opened (the file is a
directory): it starts without restored state, buffers its records, and its history reads fail with the
persistence layer's error.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import Settings
from simulator.served import Served, served_service
from tests.api.conftest import WRITE_TOKEN
from tests.db.conftest import db_url, pg_schema  # noqa: F401 - real SQLite and PostgreSQL


@pytest.fixture
def down_client(served_db_down: Served) -> Iterator[TestClient]:
    s = served_db_down
    with TestClient(create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)) as c:
        yield c


def test_list_during_an_outage_says_it_is_partial(down_client: TestClient) -> None:
    r = down_client.get("/api/v1/identifications")
    assert r.status_code == 200
    body = r.json()
    assert body["partial"] is True
    assert "database" in body["partial_reason"] and "unable to open" in body["partial_reason"]
    assert len(body["items"]) == 2  # the two identifications this process made (held for the database)
    assert [i["condition"]["speed_rpm"] for i in body["items"]] == [4000.0, 3000.0]


def test_get_during_an_outage_is_503_naming_the_database(down_client: TestClient) -> None:
    r = down_client.get("/api/v1/identifications/424242")
    assert r.status_code == 503, r.text
    err = r.json()["error"]
    assert err["code"] == "not_ready"
    assert "424242" in err["message"] and "database unavailable" in err["message"]
    assert r.headers["retry-after"]


def test_a_remembered_identification_is_served_during_an_outage(down_client: TestClient) -> None:
    newest = down_client.get("/api/v1/identifications").json()["items"][0]
    r = down_client.get(f"/api/v1/identifications/{newest['id']}")
    assert r.status_code == 200 and r.json()["id"] == newest["id"]


def test_complete_page_is_not_partial(client: TestClient) -> None:
    body = client.get("/api/v1/identifications").json()
    assert body["partial"] is False and body["partial_reason"] is None
    assert body["total"] == 2


@pytest.fixture
def db_client(db_url: str) -> Iterator[TestClient]:  # noqa: F811
    """The real service on an empty, migrated SQLite or PostgreSQL database (no samples)."""
    with (
        served_service(database_url=db_url, plan=None) as s,
        TestClient(create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)) as c,
    ):
        yield c


def test_ids_at_the_bigint_edge_on_a_real_database(db_client: TestClient) -> None:
    """2**63 - 1 reaches the database and is simply not there; 2**63 is refused before (it overflowed)."""
    assert db_client.get(f"/api/v1/identifications/{2**63 - 1}").status_code == 404
    r = db_client.get(f"/api/v1/identifications/{2**63}")
    assert r.status_code == 422 and r.json()["error"]["field"] == "identification_id"


@pytest.mark.parametrize(
    "since", ["0001-01-01T00:00:00Z", "9999-12-31T23:59:59Z", "0001-01-01T00:00:00-10:00"]
)
def test_extreme_times_on_a_real_database_are_complete_pages(db_client: TestClient, since: str) -> None:
    r = db_client.get("/api/v1/identifications", params={"since": since})
    assert r.status_code == 200, r.text
    assert r.json()["partial"] is False
