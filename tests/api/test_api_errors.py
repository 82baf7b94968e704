"""Every error path returns the one JSON error shape; 422 names the field."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from api.routers.field import MAX_POINTS


def _error(r: object) -> dict:  # type: ignore[type-arg]
    body = r.json()  # type: ignore[attr-defined]
    assert set(body) == {"error"}
    assert set(body["error"]) == {"code", "message", "field", "detail"}
    return body["error"]  # type: ignore[no-any-return]


@pytest.mark.parametrize(
    ("path", "params", "field"),
    [
        ("/api/v1/temperature-field", {"format": "bogus"}, "format"),
        ("/api/v1/temperature-field", {"at": "yesterday"}, "at"),
        ("/api/v1/temperature-field", {"format": "grid", "nr": 500}, "nr"),
        ("/api/v1/temperature-field", {"format": "grid", "nz": 1}, "nz"),
        ("/api/v1/temperature-field", {"format": "points", "points": "0.01,0.1;abc"}, "points"),
        ("/api/v1/temperature-field", {"format": "points", "points": "0.01,0.1,0.3"}, "points"),
        ("/api/v1/temperature-field", {"format": "points", "points": "nan,0.1"}, "points"),
        ("/api/v1/temperature-field", {"format": "points"}, "points"),
        ("/api/v1/temperature-field", {"format": "mesh", "points": "0.01,0.1"}, "points"),
        ("/api/v1/sensors", {"channels": "1,x"}, "channels"),
        ("/api/v1/sensors", {"channels": "0"}, "channels"),
        ("/api/v1/sensors", {"channels": "99"}, "channels"),
        ("/api/v1/sensors", {"channels": "1,33"}, "channels"),
        ("/api/v1/condition", {"limit": 0}, "limit"),
        ("/api/v1/identifications", {"limit": 1000}, "limit"),
        ("/api/v1/identifications", {"offset": -1}, "offset"),
        ("/api/v1/identifications", {"since": "2026-01-01T00:00:00"}, "since"),
        ("/api/v1/identifications", {"since": "not a date"}, "since"),
        (
            "/api/v1/identifications",
            {"since": "2026-01-02T00:00:00Z", "until": "2026-01-01T00:00:00Z"},
            "until",
        ),
        ("/api/v1/identifications/abc", {}, "identification_id"),
        ("/api/v1/identifications/0", {}, "identification_id"),
        ("/api/v1/identifications/9223372036854775808", {}, "identification_id"),
        ("/api/v1/identifications", {"until": "0.5"}, "until"),
        ("/api/v1/identifications", {"since": "1700000000"}, "since"),
        ("/api/v1/identifications", {"since": "0001-01-01T00:00:00+01:00"}, "since"),
    ],
)
def test_422_names_the_field(ro_client: TestClient, path: str, params: dict[str, object], field: str) -> None:
    r = ro_client.get(path, params=params)
    assert r.status_code == 422, r.text
    err = _error(r)
    assert err["code"] == "invalid"
    assert err["field"] == field
    assert err["message"].startswith(field)


def test_too_many_points_is_422(ro_client: TestClient) -> None:
    pts = ";".join(["0.02,0.1"] * (MAX_POINTS + 1))
    r = ro_client.get("/api/v1/temperature-field", params={"format": "points", "points": pts})
    assert r.status_code == 422 and _error(r)["field"] == "points"
    pts_ok = ";".join(["0.02,0.1"] * MAX_POINTS)
    assert (
        ro_client.get("/api/v1/temperature-field", params={"format": "points", "points": pts_ok}).status_code
        == 200
    )


def test_unknown_identification_is_404(ro_client: TestClient) -> None:
    r = ro_client.get("/api/v1/identifications/999")
    assert r.status_code == 404
    assert _error(r)["code"] == "not_found"
    assert "999" in _error(r)["message"]


def test_unknown_route_and_wrong_method_use_the_shape(ro_client: TestClient) -> None:
    assert _error(ro_client.get("/api/v1/nothing-here"))["code"] == "not_found"
    r = ro_client.delete("/api/v1/chtc")
    assert r.status_code == 405 and _error(r)["code"] == "method_not_allowed"
