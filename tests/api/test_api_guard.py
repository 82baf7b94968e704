"""The request guard: authentication before the body, body and URL caps, 405 ``Allow``, HEAD, 500 shape."""

from __future__ import annotations

import logging
import socket
import time
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.guard import GuardLimits
from service.settings import Settings
from service.shell.service import SoftSensorService
from tests.api.conftest import WRITE_TOKEN, LiveServer, ManualClock

AUTH = {"Authorization": f"Bearer {WRITE_TOKEN}"}
POST = "/api/v1/identifications"


def _error(r: object) -> dict:  # type: ignore[type-arg]
    body = r.json()  # type: ignore[attr-defined]
    assert set(body) == {"error"}
    assert set(body["error"]) == {"code", "message", "field", "detail"}
    return body["error"]  # type: ignore[no-any-return]


def test_malformed_json_without_token_is_401(ro_client: TestClient) -> None:
    r = ro_client.post(POST, content=b'{"reason": ', headers={"Content-Type": "application/json"})
    assert r.status_code == 401, r.text
    assert _error(r)["field"] == "Authorization"


def test_malformed_json_with_token_names_the_body_and_position(ro_client: TestClient) -> None:
    r = ro_client.post(POST, content=b'{"reason": ', headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 422
    err = _error(r)
    assert err["field"] == "body"
    assert err["message"].startswith("body: invalid JSON at character 11")


def test_body_over_the_cap_is_413_before_the_route(ro_client: TestClient) -> None:
    big = b'{"reason": "' + b"x" * 10_000 + b'"}'
    r = ro_client.post(POST, content=big, headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 413
    assert _error(r)["code"] == "too_large"
    assert r.headers["connection"] == "close"


def test_chunked_body_over_the_cap_is_413(ro_client: TestClient) -> None:
    def chunks():  # type: ignore[no-untyped-def]
        yield b'{"reason": "'
        for _ in range(10):
            yield b"x" * 1000
        yield b'"}'

    r = ro_client.post(POST, content=chunks(), headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 413 and _error(r)["code"] == "too_large"


def test_wrong_method_lists_every_method_of_the_path(ro_client: TestClient) -> None:
    r = ro_client.delete(POST)
    assert r.status_code == 405
    assert r.headers["allow"] == "GET, HEAD, POST"
    assert _error(r)["code"] == "method_not_allowed"
    r = ro_client.request("TRACE", "/api/v1/chtc")
    assert r.status_code == 405 and r.headers["allow"] == "GET, HEAD"


def test_head_on_a_get_route_gives_the_headers_without_body(ro_client: TestClient) -> None:
    get = ro_client.get("/api/v1/chtc")
    head = ro_client.head("/api/v1/chtc")
    assert head.status_code == 200
    assert head.content == b""
    assert head.headers["etag"] == get.headers["etag"]
    assert head.headers["content-type"] == "application/json"


def test_oversized_url_is_414_in_the_error_shape(
    ro_service: SoftSensorService, ro_clock: ManualClock
) -> None:
    limits = GuardLimits(max_url_bytes=2000)
    with TestClient(
        create_app(Settings(api={"token": WRITE_TOKEN}), ro_service, clock=ro_clock, limits=limits)
    ) as c:
        assert c.get("/api/v1/sensors", params={"channels": "9" * 1900}).status_code == 422
        r = c.get("/api/v1/sensors", params={"channels": "9" * 2000})
    assert r.status_code == 414
    assert _error(r)["code"] == "uri_too_long"


class _Exploding:
    """The real service, except that ``condition()`` fails with an error nobody translated (the fault this
    test needs; the real service has no such path to provoke)."""

    def __init__(self, inner: SoftSensorService) -> None:
        self.inner = inner

    def condition(self) -> Any:
        raise OverflowError("Python int too large to convert to SQLite INTEGER")

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_unhandled_error_is_a_500_in_the_shape_with_one_log_line(
    ro_service: SoftSensorService, ro_clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    app = create_app(Settings(api={"token": WRITE_TOKEN}), _Exploding(ro_service), clock=ro_clock)  # type: ignore[arg-type]
    with TestClient(app) as c, caplog.at_level(logging.INFO, logger="api"):
        r = c.get("/api/v1/condition")
    assert r.status_code == 500
    assert _error(r)["code"] == "internal" and "OverflowError" in _error(r)["message"]
    records = [rec for rec in caplog.records if rec.name == "api"]
    assert len(records) == 1 and records[0].exc_info is None
    assert "OverflowError" in records[0].getMessage()


# --- against a real uvicorn server: the body is not read ---------------------------------------------
def _raw_post(port: int, headers: str, first_bytes: bytes) -> tuple[bytes, float]:
    """Send a request head and only ``first_bytes`` of a huge declared body; return the response head
    and the seconds it took to arrive."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        start = time.monotonic()
        s.sendall(headers.encode() + b"\r\n" + first_bytes)
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
        return data, time.monotonic() - start


def _head(token: str | None) -> str:
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    return (
        f"POST {POST} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        f"Content-Length: 200000000\r\n{auth}"
    )


def test_200_mb_body_is_refused_without_being_read(
    ro_service: SoftSensorService, ro_clock: ManualClock
) -> None:
    app = create_app(Settings(api={"token": WRITE_TOKEN}), ro_service, clock=ro_clock)
    with LiveServer(app) as srv:
        # 1 KB of the declared 200 MB is sent; the answer comes without waiting for the rest
        head, _ = _raw_post(srv.port, _head(None), b"{" + b" " * 1023)
        assert head.startswith(b"HTTP/1.1 401"), head
        assert b"connection: close" in head.lower()
        head, _ = _raw_post(srv.port, _head(WRITE_TOKEN), b"{" + b" " * 1023)
        assert head.startswith(b"HTTP/1.1 413"), head


def test_stalled_body_is_408(ro_service: SoftSensorService, ro_clock: ManualClock) -> None:
    limits = GuardLimits(body_timeout_s=0.3)
    app = create_app(Settings(api={"token": WRITE_TOKEN}), ro_service, clock=ro_clock, limits=limits)
    with LiveServer(app) as srv:
        head = (
            f"POST {POST} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n"
            f"Authorization: Bearer {WRITE_TOKEN}\r\n"
        )
        data, took = _raw_post(srv.port, head, b'{"reason":')
    assert data.startswith(b"HTTP/1.1 408"), data
    assert 0.25 < took < 5.0
