"""The dashboard of one spindle among several (``api.fleet.FleetDispatch``, docs/design/fleet.md): the page at
``/spindles/<id>/`` reads that spindle's API (``/api/v1/spindles/<id>/…``), in a real headless Chromium.

Spindle a's DAQ is unreachable, spindle b's service runs on good data: a's page shows the DAQ banner, b's
none; each page's verdict is its own spindle's."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

from api.app import create_app
from api.deps import ClockInfo
from api.fleet import FleetDispatch, create_fleet_app
from service.settings import Settings
from simulator.served import DEMO_FED, served_service
from tests.api.conftest import LiveServer, sqlite_url
from tests.api.test_api_dashboard import LENIENT, _attr, _banner, _case, _chromium
from tests.fakehost import bare_host


def _as(settings: Settings, sid: str) -> Settings:
    return settings.model_copy(update={"spindle": settings.spindle.model_copy(update={"id": sid})})


def _dispatch(apps: dict[str, FastAPI], clock: object) -> FleetDispatch:
    host = bare_host(clock)
    return FleetDispatch(create_fleet_app(host, apps, clock_info=ClockInfo()), apps)  # type: ignore[arg-type]


@pytest.mark.browser
def test_each_spindles_page_reads_its_own_api(chromium_path: str, tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    b_url = sqlite_url(tmp_path / "b")
    with (
        _case(tmp_path / "a", "daq-down") as sa,
        served_service(database_url=b_url, settings=LENIENT, feed_samples=DEMO_FED) as sb,
    ):
        apps = {
            "a": create_app(
                LENIENT.model_copy(update={"spindle": LENIENT.spindle.model_copy(update={"id": "a"})}),
                sa.service,
                clock=sa.clock,
            ),
            "b": create_app(
                LENIENT.model_copy(update={"spindle": LENIENT.spindle.model_copy(update={"id": "b"})}),
                sb.service,
                clock=sb.clock,
            ),
        }
        with LiveServer(_dispatch(apps, sb.clock)) as server:  # type: ignore[arg-type]
            comp = {
                sid: httpx.get(f"{server.url}/api/v1/spindles/{sid}/compensation", timeout=10).json()
                for sid in ("a", "b")
            }
            dom_a = _chromium(chromium_path, tmp_path, server.url + "/spindles/a/", "--dump-dom")
            dom_b = _chromium(chromium_path, tmp_path, server.url + "/spindles/b/", "--dump-dom")
    cls, hidden, text = _banner(dom_a)
    assert not hidden and text.strip().startswith("DAQ unreachable"), (cls, text)
    _, hidden_b, text_b = _banner(dom_b)
    assert hidden_b, text_b
    for dom, sid in ((dom_a, "a"), (dom_b, "b")):
        assert _attr(dom, "status", "data-status") == comp[sid]["status"], sid
        assert _attr(dom, "status", "data-usable") == str(comp[sid]["usable_for_compensation"]).lower(), sid
