"""The uvicorn server for the API, with limits so slow, half-sent or too many clients cannot hold it.

uvicorn's own keep-alive timeout only runs between requests: a client that connects and sends nothing, or
sends a request head a byte at a time, is held for ever. ``HeadDeadlineH11Protocol`` closes a connection
whose request head is not complete ``header_timeout_s`` after the connection opened (or after the previous
response). Bodies are the request guard's job (``api/guard.py``: size cap and per-chunk timeout).
``limit_concurrency`` bounds connections plus running requests (beyond it uvicorn answers a plain-text 503);
``h11_max_incomplete_event_size`` bounds a request head, above the guard's URL cap so that an over-long URL
still gets the JSON 414 up to that size (beyond it uvicorn answers a plain-text 400).

For TLS, client limits per address and anything facing a network, put a reverse proxy in front:
``deploy/nginx/chtc.conf`` (``docs/deployment.md``).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fastapi import FastAPI

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol


@dataclass(frozen=True, kw_only=True)
class ServerLimits:
    header_timeout_s: float = 10.0  # the request head must be complete this long after connect / last reply
    timeout_keep_alive_s: float = 5.0  # an idle keep-alive connection is closed after this
    limit_concurrency: int = 200  # connections + running requests; beyond: 503
    max_head_bytes: int = 512 * 1024  # request line + headers (h11); the guard's 414 applies below it
    backlog: int = 128


class HeadDeadlineH11Protocol(H11Protocol):
    """uvicorn's h11 protocol plus a deadline for a complete request head (see the module docstring)."""

    header_timeout_s = 10.0
    _head_deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_deadline()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        if self.conn.their_state is not h11.IDLE:  # a whole request head has arrived
            self._cancel_head_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm_head_deadline()

    def _arm_head_deadline(self) -> None:
        self._cancel_head_deadline()
        self._head_deadline = self.loop.call_later(self.header_timeout_s, self._head_timed_out)

    def _cancel_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None

    def _head_timed_out(self) -> None:
        self._head_deadline = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.close()


def server_config(
    app: FastAPI, *, host: str, port: int, limits: ServerLimits | None = None
) -> uvicorn.Config:
    """The uvicorn ``Config`` the service runs the API with (``chtc run`` / ``chtc demo``)."""
    limits = limits or ServerLimits()
    protocol = type(
        "HeadDeadlineH11", (HeadDeadlineH11Protocol,), {"header_timeout_s": limits.header_timeout_s}
    )
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        http=protocol,
        timeout_keep_alive=int(max(1, limits.timeout_keep_alive_s)),
        limit_concurrency=limits.limit_concurrency,
        h11_max_incomplete_event_size=limits.max_head_bytes,
        backlog=limits.backlog,
        log_level="warning",
        lifespan="off",
    )
