"""The hosted OPC UA server renders only the spindles that have something new (issue 43, part 5): a cell's
views wake the server's loop up to five times a second, and each update rendered every spindle (at 10
spindles 50 renders a second for 10 views; at 50, 250 for 50), each ~1 ms of Python holding the GIL beside the
REST loop (benchmarks opcua --spindles 10, docs/design/fleet.md "Hosted outlets"). Now an update renders a
spindle with a new reader, or one not rendered for ``refresh_s``; the others keep their values.
The real server and the real served service (no samples needed: a view renders without data)."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import pytest
from asyncua import Client

from service.serve.opcua.nodes import variables
from service.serve.opcua.server import OpcUaServer
from service.settings import Settings
from simulator.served import served_service

from .conftest import NS, free_port

pytestmark = pytest.mark.slow  # an OpcUaServer started per test: 10-20 s on the shared machine


def _server(refresh_s: float, clock: object) -> OpcUaServer:
    cfg = Settings(
        opcua={"enabled": True, "port": free_port(), "update_interval_s": 0.05, "refresh_s": refresh_s}
    ).opcua.for_spindle("a")
    return OpcUaServer(cfg, variables=variables(32), clock=clock, bad_after_s=60.0, spindles=["a", "b"])  # type: ignore[arg-type]


def _offer_and_wait(server: OpcUaServer, reader: object, spindle: str) -> None:
    updated = threading.Event()
    server.on_update = updated.set
    server.offer(reader, spindle)  # type: ignore[arg-type]
    assert updated.wait(10.0), "no update"


def test_an_update_renders_only_the_spindles_with_a_new_view(tmp_path: Path) -> None:
    served = served_service(database_url=f"sqlite:///{tmp_path / 'r.db'}", plan=None)
    server = _server(refresh_s=60.0, clock=served.clock)
    try:
        server.start()
        for sid in ("a", "b"):
            _offer_and_wait(server, served.service.reader(), sid)
        before = dict(server.renders)
        for _ in range(5):
            _offer_and_wait(server, served.service.reader(), "a")  # a new reader of a's each time
        assert server.renders["a"] - before["a"] == 5
        assert server.renders["b"] == before["b"]  # nothing new for b, refresh_s not reached

        async def both_objects() -> list[object]:
            async with Client(server.endpoint) as c:
                idx = await c.get_namespace_index(NS)
                nodes = [c.get_node(f"ns={idx};s={sid}.Status.Heartbeat") for sid in "ab"]
                return [(await n.read_data_value(raise_on_bad_status=False)).Value.Value for n in nodes]

        hb_a, hb_b = asyncio.run(both_objects())
        assert hb_a > hb_b > 0  # b keeps the heartbeat of its last render
    finally:
        server.stop()
        served.close()


def test_a_spindle_without_views_is_still_rendered_every_refresh_s(tmp_path: Path) -> None:
    served = served_service(database_url=f"sqlite:///{tmp_path / 'r.db'}", plan=None)
    server = _server(refresh_s=0.3, clock=served.clock)
    try:
        server.start()
        for sid in ("a", "b"):
            _offer_and_wait(server, served.service.reader(), sid)
        before = dict(server.renders)
        done = threading.Event()
        server.on_update = lambda: done.set() if server.renders["b"] >= before["b"] + 2 else None
        assert done.wait(10.0), server.renders  # b: no view, re-rendered by the refresh (ages move on)
    finally:
        server.stop()
        served.close()
