"""The API's uvicorn limits: idle and slow-header clients are dropped; an over-long URL gets the JSON 414."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
import uvicorn

from api.app import create_app
from api.server import ServerLimits, server_config
from service.settings import Settings
from service.shell.service import SoftSensorService
from tests.api.conftest import WRITE_TOKEN, ManualClock, free_port

HEADER_TIMEOUT_S = 0.5


@pytest.fixture
def server(service: SoftSensorService, clock: ManualClock) -> Iterator[int]:
    app = create_app(Settings(api={"token": WRITE_TOKEN}), service, clock=clock)
    port = free_port()
    limits = ServerLimits(header_timeout_s=HEADER_TIMEOUT_S, timeout_keep_alive_s=1.0)
    srv = uvicorn.Server(server_config(app, host="127.0.0.1", port=port, limits=limits))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10.0
    while not srv.started:
        assert time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)
    yield port
    srv.should_exit = True
    thread.join(timeout=10.0)


def _closed_after(sock: socket.socket, limit_s: float) -> float:
    """Seconds until the server closes ``sock`` (recv returns b""); fails after ``limit_s``."""
    start = time.monotonic()
    sock.settimeout(limit_s)
    while True:
        data = sock.recv(65536)
        if not data:
            return time.monotonic() - start


def test_a_silent_connection_is_closed_after_the_header_timeout(server: int) -> None:
    with socket.create_connection(("127.0.0.1", server)) as s:
        took = _closed_after(s, 5.0)
    assert HEADER_TIMEOUT_S * 0.8 < took < HEADER_TIMEOUT_S + 2.0


def test_a_head_sent_a_line_at_a_time_is_cut_off(server: int) -> None:
    with socket.create_connection(("127.0.0.1", server)) as s:
        start = time.monotonic()
        s.sendall(b"GET /api/v1/healthz HTTP/1.1\r\nHost: x\r\n")
        closed = False
        for i in range(40):  # a slow client: one header line every 0.1 s, never finishing the head
            try:
                s.sendall(f"X-Slow-{i}: 1\r\n".encode())
            except OSError:
                closed = True
                break
            s.settimeout(0.1)
            try:
                if s.recv(65536) == b"":
                    closed = True
                    break
            except TimeoutError:
                pass
        took = time.monotonic() - start
    assert closed, "the server kept a slow request head open for 4 s"
    assert took < HEADER_TIMEOUT_S + 2.0


def test_keep_alive_connection_serves_requests_then_idles_out(server: int) -> None:
    with httpx.Client(base_url=f"http://127.0.0.1:{server}") as c:
        for _ in range(3):  # the head deadline is re-armed after each reply, not a limit on the connection
            assert c.get("/api/v1/healthz").status_code == 200


def test_oversized_url_below_the_head_cap_is_the_json_414(server: int) -> None:
    target = (
        "/api/v1/sensors?channels=" + "9" * 100_000
    )  # over the guard's 64 KiB, under the 512 KiB head cap
    with socket.create_connection(("127.0.0.1", server), timeout=10) as s:
        s.sendall(f"GET {target} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        data = b""
        while b'"uri_too_long"' not in data:
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
    assert data.startswith(b"HTTP/1.1 414"), data[:200]
    assert b'"uri_too_long"' in data


def test_config_carries_the_limits() -> None:
    cfg = server_config(object(), host="127.0.0.1", port=1, limits=ServerLimits(limit_concurrency=7))
    assert cfg.limit_concurrency == 7 and cfg.h11_max_incomplete_event_size == 512 * 1024
    assert cfg.timeout_keep_alive == 5
