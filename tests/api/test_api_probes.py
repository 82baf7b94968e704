"""Root ``/healthz`` and ``/readyz`` for probes: the same answers as the ``/api/v1`` ones (issue 25)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import ApiSettings, Settings
from tests.api.conftest import ManualClock, Served

READ_TOKEN = "read-token-for-probes-tests"


def _steady(body: dict[str, object]) -> dict[str, object]:
    """The body without what moves between the two requests on its own.

    ``uptime_s`` is wall time, and a device's counters count background work: the writer's queue takes the
    service's own rows (checkpoints, results) at any moment, so ``pending`` moved between two requests made
    right after a flush (a fresh-clone CI run failed on it). Names, statuses and everything else must agree.
    """
    devices = body.get("devices")
    steady = {k: v for k, v in body.items() if k != "uptime_s"}
    if isinstance(devices, list):
        steady["devices"] = [{k: v for k, v in d.items() if k != "counters"} for d in devices]
    return steady


def test_root_probes_answer_as_the_api_ones(client: TestClient, clock: ManualClock) -> None:
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
