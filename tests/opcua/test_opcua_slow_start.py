"""A cell's OPC UA server that starts slowly but steadily is waited for; one that stops making progress is
reported (issue 43): 50 spindles' objects took over 60 s to build beside the spindles' own start on 2 cores,
and the fixed 60-s start timeout ended the whole host. The real server, its object builder slowed down."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime
from typing import Any

import pytest

from service.serve.errors import OutletError
from service.serve.opcua import server as opcua_server
from service.serve.opcua.nodes import variables
from service.serve.opcua.server import OpcUaServer
from service.settings import Settings

from .conftest import free_port

pytestmark = pytest.mark.slow  # an OpcUaServer started per test


def _server(spindles: list[str]) -> OpcUaServer:
    cfg = Settings(opcua={"enabled": True, "port": free_port()}).opcua.for_spindle(spindles[0])
    return OpcUaServer(
        cfg, variables=variables(32), clock=lambda: datetime.now(UTC), bad_after_s=60.0, spindles=spindles
    )


def _slowed(monkeypatch: pytest.MonkeyPatch, delay_s: float) -> None:
    real = opcua_server.add_instance

    async def slow(*args: Any, **kwargs: Any) -> Any:
        await asyncio.sleep(delay_s)
        return await real(*args, **kwargs)

    monkeypatch.setattr(opcua_server, "add_instance", slow)


def test_a_start_longer_than_the_stall_limit_is_waited_for_while_it_progresses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _slowed(monkeypatch, 2.0)  # 4 more objects: over 8 s of start, each step well within 5 s
    server = _server([f"s{i}" for i in range(5)])
    try:
        server.start(stall_s=5.0)
        assert server.start_steps == server.start_total == 3 * 5 + 2
    finally:
        server.stop()


def test_a_start_without_progress_is_reported_with_how_far_it_got(monkeypatch: pytest.MonkeyPatch) -> None:
    _slowed(monkeypatch, 6.0)  # the second object takes far longer than the stall limit
    server = _server(["a", "b", "c"])
    try:
        with pytest.raises(OutletError, match=r"no progress for 2 s \([0-2] of 11 start steps done\)"):
            server.start(stall_s=2.0)
    finally:
        server.stop()
