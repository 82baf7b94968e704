"""Root ``/healthz`` and ``/readyz`` for probes: the same answers as the ``/api/v1`` ones (issue 25)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import ApiSettings, Settings
from tests.api.conftest import ManualClock, Served

READ_TOKEN = "read-token-for-probes-tests"


def _steady(body: dict[str, object]) -> dict[str, object]:
    """The body without ``uptime_s`` (wall time: it moves between the two requests)."""
    return {k: v for k, v in body.items() if k != "uptime_s"}


def test_root_probes_answer_as_the_api_ones(client: TestClient, clock: ManualClock, served: Served) -> None:
    writer = served.persistence.sink.writer
    assert writer is not None and writer.flush()  # the fed samples written: the db's counters hold still
    for path in ("/healthz", "/readyz"):
        root, api = client.get(path), client.get(f"/api/v1{path}")
        assert root.status_code == api.status_code == 200
        assert _steady(root.json()) == _steady(api.json())
        assert client.head(path).status_code == 200
    clock.advance(120)  # data too old: not ready, on both paths
    root, api = client.get("/readyz"), client.get("/api/v1/readyz")
    assert root.status_code == api.status_code == 503
    assert root.json() == api.json() and root.headers["Retry-After"] == "5"


def test_root_probes_stay_open_with_a_read_token_and_out_of_the_schema(served: Served) -> None:
    settings = Settings(api=ApiSettings(read_token=READ_TOKEN))
    with TestClient(create_app(settings, served.service, clock=served.clock)) as c:
        assert c.get("/api/v1/chtc").status_code == 401  # reads need the token...
        assert c.get("/healthz").status_code == 200  # ...probes do not
        assert c.get("/readyz").status_code == 200
        assert c.post("/healthz").status_code == 405
        auth = {"Authorization": f"Bearer {READ_TOKEN}"}
        paths = c.get("/api/v1/openapi.json", headers=auth).json()["paths"]
    assert "/api/v1/healthz" in paths and "/healthz" not in paths and "/readyz" not in paths
