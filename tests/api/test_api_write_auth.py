"""POST /identifications, jobs, and the bearer-token rules for writes and (optional) reads."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import Settings
from service.shell.service import SoftSensorService
from simulator.served import Served, served_service
from tests.api.conftest import WRITE_TOKEN, ManualClock, sqlite_url
from tests.modes import PER_CONDITION

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}
READ_TOKEN = "read-token-for-tests"


def _error(r: object) -> dict:  # type: ignore[type-arg]
    body = r.json()  # type: ignore[attr-defined]
    assert set(body) == {"error"}
    assert set(body["error"]) == {"code", "message", "field", "detail"}
    return body["error"]  # type: ignore[no-any-return]


def test_post_without_token_is_401(ro_client: TestClient) -> None:
    r = ro_client.post("/api/v1/identifications")
    assert r.status_code == 401
    assert r.headers["www-authenticate"] == "Bearer"
    assert _error(r)["field"] == "Authorization"


def test_post_with_other_scheme_is_401(ro_client: TestClient) -> None:
    r = ro_client.post("/api/v1/identifications", headers={"Authorization": f"Basic {WRITE_TOKEN}"})
    assert r.status_code == 401


def test_post_with_wrong_token_is_403(ro_client: TestClient) -> None:
    r = ro_client.post("/api/v1/identifications", headers={"Authorization": "Bearer nope"})
    assert r.status_code == 403
    assert _error(r)["code"] == "forbidden"


def test_post_when_no_token_configured_is_403(ro_service: SoftSensorService, ro_clock: ManualClock) -> None:
    with TestClient(create_app(Settings(), ro_service, clock=ro_clock)) as c:
        r = c.post("/api/v1/identifications", headers=AUTH)
    assert r.status_code == 403
    assert "no API token" in _error(r)["message"]


def test_post_starts_a_job_then_busy_then_done(client: TestClient, served: Served) -> None:
    served.worker.hold()  # the job waits in the worker until released: "running" for as long as needed
    r = client.post("/api/v1/identifications", headers=AUTH, json={"reason": "operator check"})
    assert r.status_code == 202
    job = r.json()
    # the window is cut when the job is accepted: it is running from then on (never "queued")
    assert job["state"] == "running" and job["reason"] == "operator check"
    assert r.headers["location"] == job["href"]
    busy = client.post("/api/v1/identifications", headers=AUTH)
    assert busy.status_code == 409 and _error(busy)["code"] == "busy"
    assert client.get("/api/v1/chtc").json()["status"] == "identifying"
    served.worker.release()
    served.settle()
    done = client.get(job["href"]).json()
    assert done["state"] == "done" and done["identification_id"] == 3
    rec = client.get(f"/api/v1/identifications/{done['identification_id']}").json()
    assert rec["reason"] == "operator check" and rec["outcome"] == "ok"
    chtc = client.get("/api/v1/chtc").json()
    assert chtc["identification_id"] == 3 and chtc["status"] == "fresh"


def test_post_body_is_validated(ro_client: TestClient) -> None:
    r = ro_client.post("/api/v1/identifications", headers=AUTH, json={"reason": "x", "force": True})
    assert r.status_code == 422 and _error(r)["field"] == "force"
    r = ro_client.post("/api/v1/identifications", headers=AUTH, json={"reason": "<script>"})
    assert r.status_code == 422 and _error(r)["field"] == "reason"


def test_post_when_not_ready_is_503(tmp_path: Path) -> None:
    """No sample yet: nothing to identify from."""
    with served_service(database_url=sqlite_url(tmp_path), feed_samples=0) as s:
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        with TestClient(app) as c:
            r = c.post("/api/v1/identifications", headers=AUTH)
    assert r.status_code == 503 and _error(r)["code"] == "not_ready"
    assert "no samples" in _error(r)["message"]


def test_post_while_the_model_loads_is_503_then_accepted(tmp_path: Path) -> None:
    """Samples are there, but the worker is still loading the model: a manual job could not run yet."""
    # a manual job needs min_window_s of the condition's data; no scheduled job (it would wait for the model);
    # per-condition mode: a manual map fit would need map_min_window_min (10 min) of data instead
    ident = {"min_window_s": 120.0, "schedule_min": (30.0,)}
    settings = Settings(identification={**ident, **PER_CONDITION})
    with served_service(database_url=sqlite_url(tmp_path), settings=settings, loading=True) as s:
        s.feed_next(20)  # 200 s of the first condition: only the loading model stands in the way
        app = create_app(Settings(api={"token": WRITE_TOKEN}), s.service, clock=s.clock)
        with TestClient(app) as c:
            r = c.post("/api/v1/identifications", headers=AUTH)
            assert r.status_code == 503 and _error(r)["code"] == "not_ready"
            assert "model is still loading" in _error(r)["message"]
            assert s.service.view.jobs == {}  # refused before the core: no job was made
            s.started()
            r = c.post("/api/v1/identifications", headers=AUTH)
            assert r.status_code == 202, r.text
            s.settle()
            assert c.get(r.json()["href"]).json()["state"] != "running"


def test_unknown_job_is_404(ro_client: TestClient) -> None:
    r = ro_client.get("/api/v1/identifications/jobs/job-99")
    assert r.status_code == 404 and _error(r)["code"] == "not_found"


def test_read_token_guards_reads_but_not_probes(ro_service: SoftSensorService, ro_clock: ManualClock) -> None:
    settings = Settings(api={"token": WRITE_TOKEN, "read_token": READ_TOKEN})
    with TestClient(create_app(settings, ro_service, clock=ro_clock)) as c:
        assert c.get("/api/v1/chtc").status_code == 401
        assert c.get("/api/v1/chtc", headers={"Authorization": "Bearer wrong"}).status_code == 403
        assert c.get("/api/v1/chtc", headers={"Authorization": f"Bearer {READ_TOKEN}"}).status_code == 200
        assert c.get("/api/v1/sensors", headers=AUTH).status_code == 200
        assert c.get("/api/v1/metrics").status_code == 401
        assert c.get("/api/v1/healthz").status_code == 200
        assert c.get("/api/v1/readyz").status_code == 200
        assert c.get("/").status_code == 200
        # the read token does not allow writes
        assert (
            c.post("/api/v1/identifications", headers={"Authorization": f"Bearer {READ_TOKEN}"}).status_code
            == 403
        )
