"""The OpenAPI documents of an instance hosting several spindles (issue 41 item 12): a spindle's
``/api/v1/spindles/{id}/openapi.json`` listed ``/api/v1/chtc`` and the others, which are 404 on a host, and
the host served no OpenAPI of its own."""

from __future__ import annotations

from fastapi.testclient import TestClient

from api.app import create_app
from api.deps import ClockInfo
from api.fleet import FleetDispatch, create_fleet_app
from service.settings import Settings
from tests.fakehost import bare_host


def _client(ids: tuple[str, ...]) -> TestClient:
    apps = {}
    for sid in ids:
        s = Settings()
        own = s.model_copy(update={"spindle": s.spindle.model_copy(update={"id": sid})})
        apps[sid] = create_app(own, None)
    host = bare_host()
    return TestClient(FleetDispatch(create_fleet_app(host, apps, clock_info=ClockInfo()), apps))  # type: ignore[arg-type]


def test_a_spindles_document_lists_the_paths_the_host_serves_for_it() -> None:
    client = _client(("a", "b"))
    doc = client.get("/api/v1/spindles/a/openapi.json").json()
    paths = list(doc["paths"])
    assert "/api/v1/spindles/a/chtc" in paths and "/api/v1/spindles/a/compensation" in paths
    assert all(p.startswith("/api/v1/spindles/a/") for p in paths), paths
    # and each of them is served: a read that needs no service state answers (not the host's 404)
    assert client.get("/api/v1/spindles/a/openapi.json").status_code == 200
    assert client.get("/api/v1/chtc").status_code == 404  # on a host, the unprefixed path is not served


def test_the_host_serves_its_own_document_with_the_unknown_spindles_404() -> None:
    client = _client(("a", "b"))
    doc = client.get("/api/v1/openapi.json").json()
    assert doc["info"]["title"] == "spindle-chtc (host)"
    assert "/api/v1/spindles" in doc["paths"] and "/api/v1/healthz" in doc["paths"]
    per_spindle = doc["paths"]["/api/v1/spindles/{spindle_id}/openapi.json"]["get"]["responses"]
    assert "404" in per_spindle
    assert client.get("/api/v1/spindles/zz/openapi.json").status_code == 404


def test_one_spindle_keeps_its_document_at_the_root() -> None:
    client = _client(("a",))
    assert "/api/v1/chtc" in client.get("/api/v1/openapi.json").json()["paths"]
