"""The API benchmark's load generator against a live server (a smoke test: the figures are not checked)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import pytest

from api.app import create_app
from benchmarks._api_load import RawClient, _load, histogram_quantile
from service.settings import Settings
from simulator.served import Served
from tests.api.conftest import LiveServer


@pytest.fixture(scope="module")
def server(served_ro: Served) -> Iterator[LiveServer]:
    with LiveServer(create_app(Settings(), served_ro.service, clock=served_ro.clock)) as s:
        yield s


def test_raw_client_reads_status_and_whole_bodies(server: LiveServer) -> None:
    async def go() -> list[int]:
        ok, missing = RawClient(server.url + "/api/v1/chtc"), RawClient(server.url + "/api/v1/nothing")
        try:  # twice on the same keep-alive connection: the first body must have been consumed fully
            return [await ok.get(), await ok.get(), await missing.get()]
        finally:
            await ok.aclose()
            await missing.aclose()

    assert asyncio.run(go()) == [200, 200, 404]


@pytest.mark.parametrize("kind", ["raw", "httpx"])
def test_open_loop_load_sends_the_scheduled_requests(server: LiveServer, kind: str) -> None:
    r = asyncio.run(_load(server.url + "/api/v1/chtc", rate=100.0, duration_s=0.3, clients=3, kind=kind))
    assert r["requests"] == 30 and r["errors"] == 0
    assert 0 < r["p50_ms"] <= r["p99_ms"] <= r["max_ms"]


def test_histogram_quantile_interpolates_like_prometheus() -> None:
    before = {0.001: 10.0, 0.002: 10.0, math.inf: 10.0}
    after = {0.001: 60.0, 0.002: 110.0, math.inf: 110.0}  # 50 obs in (0, 1 ms], 50 in (1, 2 ms]
    assert histogram_quantile(0.5, before, after) == pytest.approx(0.001)
    assert histogram_quantile(0.99, before, after) == pytest.approx(0.001 + 0.001 * 49 / 50)
    assert histogram_quantile(0.5, after, after) is None  # nothing observed in between


def test_field_phase_loads_chtc_mesh_and_points_together(server: LiveServer) -> None:
    import argparse

    from benchmarks.api import field_phase

    args = argparse.Namespace(runs=1, duration=1.0, rate=20.0, clients=2, mesh_rate=2.0, points_rate=10.0)
    out = field_phase(server.url, args)
    assert out["errors"] == 0 and out["raw"]["runs"][0]["requests"] == 20
    assert out["mesh"]["statuses"] == {"200": 2} and out["points"]["statuses"] == {"200": 10}
