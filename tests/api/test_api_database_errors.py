"""Database failures reach the client as the error shape or a marked partial page, never a bare 500.

The real ``SoftSensorService`` history paths run against a SQLite database that cannot be opened (a file in
a directory that does not exist), so every read raises the persistence layer's ``DatabaseUnavailableError``.
"""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine
from sqlalchemy.orm import sessionmaker

from api.app import create_app
from service.service import SoftSensorService
from service.settings import Settings
from tests.api.conftest import WRITE_TOKEN, ManualClock


@pytest.fixture
def down_client(tmp_path: Path, service: Any, clock: ManualClock) -> TestClient:
    engine = create_engine(f"sqlite:///{tmp_path / 'missing-dir' / 'chtc.db'}")
    in_memory = list(service.list_identifications(since=None, until=None, limit=2, offset=0).items)
    # only the parts the history paths use: the lock and the records this process remembers
    core = SimpleNamespace(lock=threading.Lock(), records=in_memory)
    svc = SoftSensorService(cast(Any, core), worker=None, session_factory=sessionmaker(engine), clock=clock)
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
