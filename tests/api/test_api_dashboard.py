"""The dashboard: served by the app without any external resource, and rendered by real headless Chromium."""

from __future__ import annotations

import re
import subprocess
import threading
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import STATIC_DIR, create_app
from service.interface_memory import InMemoryService, demo_service, push_noisy_sample
from service.settings import Settings
from tests.api.conftest import LiveServer, ManualClock

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--virtual-time-budget=5000",
]


def test_dashboard_is_served_with_its_assets(client: TestClient) -> None:
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "default-src 'self'" in page.headers["content-security-policy"]
    for asset in ("/static/app.js", "/static/style.css"):
        assert asset in page.text
        assert client.get(asset).status_code == 200


def test_dashboard_loads_nothing_from_outside() -> None:
    for path in STATIC_DIR.iterdir():
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"(src|href)\s*=\s*[\"'](https?:)?//", text), path
        assert 'fetch("http' not in text and "import(" not in text, path


class _Pusher:
    """Adds a noisy sample every ``period_s`` (real time) so the chart has a history to draw."""

    def __init__(self, svc: InMemoryService, period_s: float = 0.1) -> None:
        self.svc, self.period_s = svc, period_s
        self.stop = threading.Event()
        self.rng = np.random.default_rng(3)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(self.period_s):
            push_noisy_sample(self.svc, rng=self.rng)

    def __enter__(self) -> _Pusher:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=5)


def _chromium(chromium_path: str, tmp: Path, url: str, *extra: str) -> str:
    """Run headless Chromium; fail on a JavaScript error or a CSP refusal logged to the console."""
    cmd = [chromium_path, *CHROMIUM_FLAGS, "--enable-logging=stderr", "--v=0"]
    cmd += [f"--user-data-dir={tmp / 'profile'}", *extra, url]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=90, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    js_errors = [line for line in out.stderr.splitlines() if "Uncaught" in line or "Refused to" in line]
    assert not js_errors, js_errors
    return out.stdout


@pytest.fixture
def live_demo() -> Iterator[tuple[LiveServer, InMemoryService]]:
    svc = demo_service()
    with LiveServer(create_app(Settings(), svc)) as server, _Pusher(svc):
        yield server, svc


@pytest.mark.browser
def test_dashboard_renders_h_field_and_chart_in_chromium(
    chromium_path: str, tmp_path: Path, live_demo: tuple[LiveServer, InMemoryService]
) -> None:
    server, svc = live_demo
    dom = _chromium(chromium_path, tmp_path, server.url + "/", "--dump-dom")
    assert 'data-rendered="1"' in dom, dom[:2000]
    snap = svc.chtc()
    assert snap is not None
    for name, h in zip(snap.zones, snap.h, strict=True):
        assert re.search(rf'id="h-{name}">{h:.2f}<', dom), name
    assert re.search(r'id="status" class="pill pill-fresh"[^>]*>fresh', dom), re.findall(
        r'id="status"[^<]*', dom
    )
    assert re.search(r'<div id="banner" class="banner" hidden="">', dom)
    assert "identification #2" in dom
    shot = tmp_path / "dashboard.png"
    _chromium(chromium_path, tmp_path, server.url + "/", "--window-size=1400,1500", f"--screenshot={shot}")
    assert shot.stat().st_size > 20_000  # a blank page is a few kB


@pytest.mark.browser
@pytest.mark.parametrize(
    ("status", "banner_class", "prefix"),
    [("stale", "banner", "STALE"), ("identifying", "banner banner-warn", "IDENTIFYING")],
)
def test_dashboard_shows_a_banner(
    chromium_path: str, tmp_path: Path, status: str, banner_class: str, prefix: str
) -> None:
    clock = ManualClock(datetime.now(UTC))
    svc = demo_service(clock=clock)
    if status == "stale":
        clock.advance(300)
    else:
        svc.set_condition(5000.0, 16.0, 22.0, state="changing")
    assert (snap := svc.chtc()) is not None and snap.status == status
    with LiveServer(create_app(Settings(), svc, clock=clock)) as server:
        dom = _chromium(chromium_path, tmp_path, server.url + "/", "--dump-dom")
    assert re.search(rf'id="status" class="pill pill-{status}"[^>]*>{status}', dom)
    banner = re.search(r'<div id="banner" class="([^"]*)"( hidden="")?>([^<]*)<', dom)
    assert banner is not None, dom[:1500]
    assert banner.group(1) == banner_class and banner.group(2) is None
    assert banner.group(3).startswith(prefix)
