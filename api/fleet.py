"""The REST API of an instance that hosts several spindles (``service.engine.host``; docs/design/fleet.md).

One uvicorn server, one ASGI app (:class:`FleetDispatch`) in front of one ``create_app`` per running
spindle (each with its own token checks, guard, metrics and routes, reading only its own service):

- ``/api/v1/spindles/{id}/<path>`` is the spindle's ``/api/v1/<path>`` (``…/chtc``, ``…/compensation``,
  ``…/healthz``); ``/spindles/{id}/`` is its dashboard (the page asks the API under the same prefix);
- ``/api/v1/spindles``: every hosted spindle, its status and verdict, and why a spindle is not running;
- ``/metrics`` (and ``/api/v1/metrics``): one exposition, every sample labelled ``spindle="<id>"``;
- ``/healthz``, ``/readyz`` (root and ``/api/v1``): the instance's. Live while it serves; ready once every
  running spindle's model is loaded (a spindle whose DAQ is down is not fresh but does not make the instance
  unready: a restart would not help it, and the others would be taken out of service with it);
- anything else (today's paths, ``/``): the spindle's own when the instance hosts exactly one, else a 404
  that says to use ``/api/v1/spindles/{id}/…``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.metrics_core import Metric
from starlette.types import ASGIApp, Receive, Scope, Send

from api.app import API_PREFIX, create_app
from api.deps import AuthConfig, ClockInfo, ReadAccess
from api.errors import error_body
from api.outlet import RestOutlet

if TYPE_CHECKING:
    from service.serve.interface import FleetHost
    from service.serve.outlet import OutletContext

__all__ = ["FleetDispatch", "FleetOutlet", "create_fleet_app", "fleet_outlet"]

_SPINDLE_API = re.compile(r"^/api/v1/spindles/([^/]+)(/.*)$")
_SPINDLE_PAGE = re.compile(r"^/spindles/([^/]+)(/.*)?$")
_FLEET_PATHS = frozenset(
    {"/api/v1/spindles", "/api/v1/spindles/", "/metrics", "/api/v1/metrics", "/healthz", "/readyz"}
    | {"/api/v1/healthz", "/api/v1/readyz"}
)


class MergedMetrics:
    """The spindles' exposed families merged by name (a family's samples from every spindle, its HELP and
    TYPE once), so ``/metrics`` stays one valid exposition."""

    def __init__(self, apps: Mapping[str, FastAPI]) -> None:
        self.apps = apps

    def collect(self) -> Iterator[Metric]:
        merged: dict[str, Metric] = {}
        for app in self.apps.values():
            for fam in app.state.metrics.exposed.collect():
                out = merged.get(fam.name)
                if out is None:
                    out = merged[fam.name] = Metric(fam.name, fam.documentation, fam.type, fam.unit)
                out.samples.extend(fam.samples)
        yield from merged.values()


def create_fleet_app(host: FleetHost, apps: Mapping[str, FastAPI], *, clock_info: ClockInfo) -> FastAPI:
    """The instance's own answers (list, health, readiness, metrics); no spindle's routes. The list and the
    metrics honour ``[api] read_token`` as every spindle's reads do."""
    app = FastAPI(title="spindle-chtc (host)", version="1", openapi_url=None, docs_url=None, redoc_url=None)
    app.state.auth = AuthConfig.from_settings(host.settings.api)
    app.state.clock_info = clock_info
    metrics = MergedMetrics(apps)

    def spindle_rows() -> list[dict[str, Any]]:
        rows = []
        for sid, hosted in host.spindles.items():
            row: dict[str, Any] = {
                "id": sid,
                "description": hosted.description,
                "running": hosted.runtime is not None,
                "error": hosted.error,
                "api": f"{API_PREFIX}/spindles/{sid}/",
                "dashboard": f"/spindles/{sid}/",
            }
            service = hosted.service
            if service is not None:
                ready = service.ready()  # type: ignore[attr-defined]
                comp = service.reader().compensation()  # type: ignore[attr-defined]
                row.update(
                    ready=ready.ready,
                    reasons=list(ready.reasons),
                    status=None if comp is None else str(comp.status),
                    usable_for_compensation=False if comp is None else comp.usable_for_compensation,
                )
            rows.append(row)
        return rows

    @app.get("/api/v1/spindles", dependencies=[ReadAccess])
    @app.get("/api/v1/spindles/", dependencies=[ReadAccess])
    async def spindles() -> JSONResponse:
        return JSONResponse({"t": host.clock().isoformat(), "spindles": spindle_rows()})

    @app.get("/healthz")
    @app.get("/api/v1/healthz")
    async def healthz() -> JSONResponse:
        running = [h.id for h in host.spindles.values() if h.runtime is not None]
        return JSONResponse(
            {
                "status": "ok" if not host.failed else "degraded",
                "t": host.clock().isoformat(),
                "spindles": len(host.spindles),
                "running": running,
                "failed": host.failed,
            }
        )

    @app.get("/readyz")
    @app.get("/api/v1/readyz")
    async def readyz() -> JSONResponse:
        waiting = [
            h.id
            for h in host.spindles.values()
            if h.runtime is not None and not getattr(h.runtime.service, "model_loaded", False)
        ]
        body = {"ready": not waiting and bool(apps), "loading": waiting, "t": host.clock().isoformat()}
        if body["ready"]:
            return JSONResponse(body)
        msg = (
            "not ready: models loading for " + ", ".join(waiting) if waiting else "not ready: no spindle runs"
        )
        return JSONResponse(
            error_body("not_ready", msg, detail=body), status_code=503, headers={"Retry-After": "5"}
        )

    @app.get("/metrics", dependencies=[ReadAccess])
    @app.get("/api/v1/metrics", dependencies=[ReadAccess])
    def metrics_route() -> Response:
        return Response(generate_latest(metrics), media_type=CONTENT_TYPE_LATEST)

    app.state.merged_metrics = metrics
    return app


class FleetDispatch:
    """The ASGI app in front (see the module docstring)."""

    def __init__(self, fleet: FastAPI, apps: Mapping[str, FastAPI]) -> None:
        self.fleet = fleet
        self.apps = apps

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.fleet(scope, receive, send)
            return
        path: str = scope["path"]
        if m := _SPINDLE_API.match(path):
            await self._to_spindle(m.group(1), API_PREFIX + m.group(2), scope, receive, send)
            return
        if m := _SPINDLE_PAGE.match(path):
            await self._to_spindle(m.group(1), m.group(2) or "/", scope, receive, send)
            return
        if path in _FLEET_PATHS:
            await self.fleet(scope, receive, send)
            return
        if len(self.apps) == 1:  # one spindle: today's paths are its own
            await next(iter(self.apps.values()))(scope, receive, send)
            return
        if path.startswith("/static/") and self.apps:  # the dashboard's files (the same for every spindle)
            await next(iter(self.apps.values()))(scope, receive, send)
            return
        await _not_found(
            send,
            f"this instance hosts {len(self.apps)} spindles: use /api/v1/spindles/{{id}}/... "
            "(the list: /api/v1/spindles)",
        )

    async def _to_spindle(self, sid: str, path: str, scope: Scope, receive: Receive, send: Send) -> None:
        app = self.apps.get(sid)
        if app is None:
            await _not_found(
                send, f"no running spindle {sid!r} on this instance (the list: /api/v1/spindles)"
            )
            return
        await app({**scope, "path": path, "raw_path": path.encode()}, receive, send)


async def _not_found(send: Send, message: str) -> None:
    import json

    body = json.dumps(error_body("not_found", message, field="spindle")).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 404,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        }
    )
    await send({"type": "http.response.body", "body": body})


class FleetOutlet(RestOutlet):
    """uvicorn serving :class:`FleetDispatch` on ``[api] host:port`` (the ``"rest_fleet"`` outlet); the
    context's ``service`` is the ``service.engine.host.Host``."""

    name = "rest_fleet"

    def __init__(self, ctx: OutletContext) -> None:
        super().__init__(ctx)
        self.apps: dict[str, FastAPI] = {}

    def build_app(self, info: ClockInfo) -> ASGIApp:
        ctx = self.ctx
        host: FleetHost = ctx.service
        for sid, hosted in host.spindles.items():
            if hosted.runtime is not None and hosted.runtime.service is not None:
                service = hosted.runtime.service
                self.apps[sid] = create_app(hosted.settings, service, clock=ctx.clock, clock_info=info)
        return FleetDispatch(create_fleet_app(host, self.apps, clock_info=info), self.apps)


def fleet_outlet(ctx: OutletContext) -> FleetOutlet:
    """The ``"rest_fleet"`` entry of ``service.serve.outlet.OUTLETS``."""
    return FleetOutlet(ctx)
