"""Database failures reach the client as the error shape or a marked partial page, never a bare 500.

The real ``SoftSensorService`` history paths run against a SQLite database that cannot be opened (a file in
a directory that does not exist), so every read raises the persistence layer's ``DatabaseUnavailableError``.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine
from sqlalchemy.orm import sessionmaker

from api.app import create_app
from model.geometry import load_spindle
from service.engine.shell import SoftSensorService
from service.settings import Settings
from tests.api.conftest import WRITE_TOKEN, ManualClock
from tests.db.conftest import db_url, engine, factory, pg_schema  # noqa: F401 - real SQLite and PostgreSQL

# the spindle description (the service's sensor-history buffer names its channels from it)
_MODEL = SimpleNamespace(spec=load_spindle())


@pytest.fixture
def down_client(tmp_path: Path, service: Any, clock: ManualClock) -> TestClient:
    dead = create_engine(f"sqlite:///{tmp_path / 'missing-dir' / 'chtc.db'}")
    in_memory = list(service.list_identifications(since=None, until=None, limit=2, offset=0).items)
    # only the parts the history paths use: the records this process remembers (in the core's view)
    core = SimpleNamespace(view=lambda: SimpleNamespace(records=tuple(in_memory)), model=_MODEL)
    svc = SoftSensorService(cast(Any, core), worker=None, session_factory=sessionmaker(dead), clock=clock)
    return TestClient(create_app(Settings(api={"token": WRITE_TOKEN}), cast(Any, svc), clock=clock))


def test_list_during_an_outage_says_it_is_partial(down_client: TestClient) -> None:
    r = down_client.get("/api/v1/identifications")
    assert r.status_code == 200
    body = r.json()
    assert body["partial"] is True
    assert "database" in body["partial_reason"] and "unable to open" in body["partial_reason"]
    assert len(body["items"]) == 2


def test_get_during_an_outage_is_503_naming_the_database(down_client: TestClient) -> None:
    r = down_client.get("/api/v1/identifications/424242")
    assert r.status_code == 503, r.text
    err = r.json()["error"]
    assert err["code"] == "not_ready"
    assert "424242" in err["message"] and "database unavailable" in err["message"]
    assert r.headers["retry-after"]


def test_complete_page_is_not_partial(client: TestClient) -> None:
    body = client.get("/api/v1/identifications").json()
    assert body["partial"] is False and body["partial_reason"] is None


@pytest.fixture
def db_client(factory: Any, clock: ManualClock) -> TestClient:  # noqa: F811
    core = SimpleNamespace(view=lambda: SimpleNamespace(records=()), model=_MODEL)
    svc = SoftSensorService(cast(Any, core), worker=None, session_factory=factory, clock=clock)
    return TestClient(create_app(Settings(api={"token": WRITE_TOKEN}), cast(Any, svc), clock=clock))


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
