"""The OpenAPI document describes the API as it answers: the error shape, the bearer scheme, every route."""

from __future__ import annotations

import json
from typing import Any

from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import Settings
from service.shell.service import SoftSensorService
from tests.api.conftest import WRITE_TOKEN, ManualClock

ERROR_REF = {"$ref": "#/components/schemas/Error"}


def _doc(client: TestClient) -> dict[str, Any]:
    r = client.get("/api/v1/openapi.json")
    assert r.status_code == 200
    return r.json()  # type: ignore[no-any-return]


def _operations(doc: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [(p, m, op) for p, ops in doc["paths"].items() for m, op in ops.items()]


def test_every_error_uses_the_error_shape(ro_client: TestClient) -> None:
    doc = _doc(ro_client)
    assert "HTTPValidationError" not in doc["components"]["schemas"]
    error = doc["components"]["schemas"]["Error"]
    assert error["required"] == ["error"]
    body = doc["components"]["schemas"]["ErrorBody"]
    assert set(body["properties"]) == {"code", "message", "field", "detail"}
    for path, method, op in _operations(doc):
        for status, response in op["responses"].items():
            if int(status) >= 400:
                assert response["content"]["application/json"]["schema"] == ERROR_REF, (path, method, status)
        if op.get("parameters"):
            assert "422" in op["responses"], (path, method)
        assert "414" in op["responses"]


def test_statuses_where_they_occur(ro_client: TestClient) -> None:
    ops = {(p, m): op["responses"] for p, m, op in _operations(_doc(ro_client))}
    post = ops[("/api/v1/identifications", "post")]
    assert {"400", "401", "403", "408", "409", "413", "422", "503"} <= set(post)
    assert post["401"]["headers"]["WWW-Authenticate"]
    assert "404" in ops[("/api/v1/identifications/{identification_id}", "get")]
    assert "404" in ops[("/api/v1/identifications/jobs/{job_id}", "get")]
    assert (
        "503" in ops[("/api/v1/chtc", "get")]
        and "Retry-After" in ops[("/api/v1/chtc", "get")]["503"]["headers"]
    )
    assert "401" not in ops[("/api/v1/chtc", "get")]  # reads are open without a read token
    comp = ops[("/api/v1/compensation", "get")]
    assert "Retry-After" in comp["503"]["headers"] and "401" not in comp
    assert comp["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/CompensationOut")
    assert "text/plain" in ops[("/api/v1/metrics", "get")]["200"]["content"]
    assert "404" in ops[("/api/v1/compensation/reference", "get")]
    assert {"401", "403", "409", "422"} <= set(ops[("/api/v1/compensation/reference", "post")])
    assert {"401", "403", "409", "422"} <= set(ops[("/api/v1/compensation/mechanics", "post")])
    assert "404" in ops[("/api/v1/compensation/mechanics", "get")]
    assert {"401", "403", "422"} <= set(ops[("/api/v1/compensation/measurements", "post")])
    assert "mechanics_uncalibrated" in json.dumps(_doc(ro_client)["components"]["schemas"]["Reason"])


def test_bearer_scheme_on_writes_and_on_reads_when_a_read_token_is_set(
    ro_client: TestClient, ro_service: SoftSensorService, ro_clock: ManualClock
) -> None:
    doc = _doc(ro_client)
    assert doc["components"]["securitySchemes"]["bearerAuth"] == {"type": "http", "scheme": "bearer"}
    secured = {(p, m) for p, m, op in _operations(doc) if op.get("security")}
    assert secured == {
        ("/api/v1/identifications", "post"),
        ("/api/v1/sensors/baseline", "post"),
        ("/api/v1/compensation/reference", "post"),
        ("/api/v1/compensation/mechanics", "post"),
        ("/api/v1/compensation/measurements", "post"),
    }
    settings = Settings(api={"token": WRITE_TOKEN, "read_token": "read-token-for-openapi"})
    with TestClient(create_app(settings, ro_service, clock=ro_clock)) as c:
        doc = _doc(c)
    for path, method, op in _operations(doc):
        if path in ("/api/v1/healthz", "/api/v1/readyz"):
            assert not op.get("security") and "401" not in op["responses"]
        else:
            assert op["security"] == [{"bearerAuth": []}], (path, method)
            assert {"401", "403"} <= set(op["responses"])


def test_every_documented_operation_is_known_to_the_guard(ro_app: Any, ro_client: TestClient) -> None:
    """A router added to the app but not to create_app's ``modules`` would skip auth-before-body."""
    doc = _doc(ro_client)
    guarded = {(r.path, m.lower()) for r in ro_app.state.guard_rules for m in r.methods}
    assert {(p, m) for p, m, _ in _operations(doc)} <= guarded


def test_since_and_until_are_date_times_and_channels_a_pattern(ro_client: TestClient) -> None:
    ops = {(p, m): op for p, m, op in _operations(_doc(ro_client))}
    params = {x["name"]: x["schema"] for x in ops[("/api/v1/identifications", "get")]["parameters"]}
    assert any(s.get("format") == "date-time" for s in params["until"]["anyOf"])
    channels = ops[("/api/v1/sensors", "get")]["parameters"][0]["schema"]["anyOf"][0]
    assert "pattern" in channels
