"""Every answer names its spindle (issue 29): ``spindle_id`` in the read endpoints' JSON, ``Chtc-Spindle-Id``
on every answer (errors, the dashboard, the OpenAPI document included), and both in the OpenAPI document."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.spindlehdr import HEADER
from service.settings import Settings
from tests.api.conftest import WRITE_TOKEN, Served

SPINDLE = "cell3-sp07"  # not the default (spindle1): the answers must come from the settings

# the read endpoints whose JSON answer names the spindle (GET, 200 on the shared read-only service)
NAMED = (
    "/api/v1/chtc",
    "/api/v1/compensation",
    "/api/v1/compensation/section",
    "/api/v1/temperature-field",
    "/api/v1/temperature-field?format=grid&nr=4&nz=5",
    "/api/v1/temperature-field?format=points&points=0.05,0.1",
    "/api/v1/sensors",
    "/api/v1/sensors/history?limit=3",
    "/api/v1/condition",
    "/api/v1/identifications",
    "/api/v1/spindle",
    "/api/v1/healthz",
    "/healthz",
)
# the operations whose 200 schema has no spindle_id: a list, a text body, or an object also nested in another
UNNAMED = {
    "/api/v1/compensation/measurements",
    "/api/v1/metrics",
    "/api/v1/identifications/{identification_id}",
    "/api/v1/compensation/reference",
    "/api/v1/compensation/mechanics",
}


@pytest.fixture
def named_client(served_ro: Served) -> Iterator[TestClient]:
    settings = Settings(api={"token": WRITE_TOKEN}, spindle={"id": SPINDLE})
    with TestClient(create_app(settings, served_ro.service, clock=served_ro.clock)) as c:
        yield c


@pytest.mark.parametrize("path", NAMED)
def test_read_answers_name_the_spindle_in_body_and_header(named_client: TestClient, path: str) -> None:
    r = named_client.get(path)
    assert r.status_code == 200, r.text
    assert r.headers[HEADER] == SPINDLE
    body = r.json()
    assert body["spindle_id"] == SPINDLE
    if "temperature-field" not in path:  # the field bodies lead with their format or cached geometry
        assert next(iter(body)) == "spindle_id"  # first, where a reader looks


def test_cached_bodies_name_the_spindle_too(named_client: TestClient) -> None:
    """/chtc's body is cached per ETag; the second answer (from the cache) still names the spindle."""
    first = named_client.get("/api/v1/chtc")
    again = named_client.get("/api/v1/chtc")
    assert first.json()["spindle_id"] == again.json()["spindle_id"] == SPINDLE
    not_modified = named_client.get("/api/v1/chtc", headers={"If-None-Match": first.headers["etag"]})
    assert not_modified.status_code == 304 and not_modified.headers[HEADER] == SPINDLE


def test_jobs_and_readiness_name_the_spindle(named_client: TestClient) -> None:
    ready = named_client.get("/readyz")
    body = ready.json()
    inner = body if ready.status_code == 200 else body["error"]["detail"]
    assert inner["spindle_id"] == SPINDLE and ready.headers[HEADER] == SPINDLE
    job = named_client.post("/api/v1/identifications", headers={"Authorization": f"Bearer {WRITE_TOKEN}"})
    assert job.status_code in (202, 409), job.text
    if job.status_code == 202:
        assert job.json()["spindle_id"] == SPINDLE
        polled = named_client.get(job.headers["location"])
        assert polled.json()["spindle_id"] == SPINDLE


@pytest.mark.parametrize(
    ("method", "path", "status"),
    [
        ("GET", "/api/v1/identifications/999999", 404),  # a service error
        ("GET", "/api/v1/no-such-thing", 404),  # Starlette's
        ("POST", "/api/v1/identifications", 401),  # refused by the guard before the app
        ("DELETE", "/api/v1/chtc", 405),  # the guard too
        ("GET", "/api/v1/sensors?channels=99", 422),
        ("GET", "/", 200),  # the dashboard
        ("GET", "/api/v1/openapi.json", 200),
        ("HEAD", "/api/v1/chtc", 200),
    ],
)
def test_every_answer_carries_the_header(
    named_client: TestClient, method: str, path: str, status: int
) -> None:
    r = named_client.request(method, path)
    assert r.status_code == status, r.text
    assert r.headers[HEADER] == SPINDLE
    if status >= 400:
        assert set(r.json()) == {"error"}  # the error shape is unchanged: the header says which spindle


def _schema(doc: dict[str, Any], ref: dict[str, Any]) -> dict[str, Any]:
    return doc["components"]["schemas"][ref["$ref"].rsplit("/", 1)[1]]  # type: ignore[no-any-return]


def test_openapi_documents_the_member_and_the_header(named_client: TestClient) -> None:
    doc = named_client.get("/api/v1/openapi.json").json()
    checked = 0
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            for status, response in op["responses"].items():
                assert HEADER in response.get("headers", {}), (path, method, status)
            ok = op["responses"].get("200") or op["responses"].get("202")
            if method != "get" or path in UNNAMED or ok is None:
                continue
            schema = ok["content"]["application/json"]["schema"]
            for ref in schema.get("anyOf", [schema]):  # the field's three layouts
                model = _schema(doc, ref)
                assert "spindle_id" in model["required"], (path, model.get("title"))
                checked += 1
    assert checked >= 14
