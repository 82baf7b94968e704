"""The REST API as an outlet (``service.serve.outlet``): registered by name (``"rest"``) so that ``service``
never imports ``api``; the runtime loads :func:`rest_outlet` when it starts the API.

The API reads the service on each request (``ChtcService``, whose reads are the newest view's
``ViewReader``), so ``on_view`` has nothing to do.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from api.app import create_app
from api.deps import ClockInfo
from api.server import server_config

if TYPE_CHECKING:
    import uvicorn
    from starlette.types import ASGIApp

    from service.serve.outlet import OutletContext
    from service.serve.reader import ViewReader

__all__ = ["RestOutlet", "rest_outlet"]


class RestOutlet:
    """uvicorn serving ``create_app(settings, service)`` on ``[api] host:port`` in a task of the loop."""

    name = "rest"

    def __init__(self, ctx: OutletContext) -> None:
        self.ctx = ctx
        self.server: uvicorn.Server | None = None
        self.task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        import uvicorn

        ctx = self.ctx
        app = self.build_app(ClockInfo(simulated=ctx.simulated, speedup=ctx.speedup))
        config = server_config(app, host=ctx.settings.api.host, port=ctx.settings.api.port)  # type: ignore[arg-type]
        self.server = uvicorn.Server(config)
        self.task = asyncio.ensure_future(self.server.serve())

    def build_app(self, info: ClockInfo) -> ASGIApp:
        """The app served: the spindle's API and dashboard."""
        return create_app(self.ctx.settings, self.ctx.service, clock=self.ctx.clock, clock_info=info)

    def on_view(self, reader: ViewReader) -> None:
        return None  # requests read the newest view themselves

    @property
    def started(self) -> bool:
        return self.server is not None and bool(self.server.started)

    async def close(self) -> None:
        """Stop gracefully (open requests finish); a server that does not stop in 10 s is abandoned."""
        if self.server is not None:
            self.server.should_exit = True
        task = self.task
        if task is None:
            return
        # asyncio.wait, not wait_for: on a timeout wait_for cancels and then waits for the task without
        # limit, which hung the shutdown when a client library swallowed the cancellation.
        done, _ = await asyncio.wait({task}, timeout=10.0)
        if not done:
            self.ctx.on_event("shutdown: the API server did not stop within 10 s; abandoned")
        elif not task.cancelled():
            task.exception()  # retrieved: a failure at shutdown was already reported by the task


def rest_outlet(ctx: OutletContext) -> RestOutlet:
    """The ``"rest"`` entry of ``service.serve.outlet.OUTLETS``."""
    return RestOutlet(ctx)
