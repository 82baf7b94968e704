"""The REST API of an instance that hosts several spindles (``service.host.fleet``; docs/design/fleet.md).

One uvicorn server, one ASGI app (:class:`FleetDispatch`) in front of one ``create_app`` per running
spindle (each with its own token checks, guard, metrics and routes, reading only its own service):

- ``/api/v1/spindles/{id}/<path>`` is the spindle's ``/api/v1/<path>`` (``…/chtc``, ``…/compensation``,
  ``…/healthz``); ``/spindles/{id}/`` is its dashboard (the page asks the API under the same prefix);
- ``/api/v1/spindles``: every hosted spindle, its status and verdict, and why a spindle is not running;
- ``/metrics`` (and ``/api/v1/metrics``): one exposition, every sample labelled ``spindle="<id>"``;
- ``/healthz``, ``/readyz`` (root and ``/api/v1``): the instance's. Live while it serves; ready once every
  running spindle's model is loaded (a spindle whose DAQ is down is not fresh but does not make the instance
  unready: a restart would not help it, and the others would be taken out of service with it);
- ``/api/v1/openapi.json``: the instance's own OpenAPI document (its paths, and the 404 of an unknown
  spindle) when it hosts several; ``/api/v1/spindles/{id}/openapi.json`` the spindle's, with the paths a host
  serves for it (``/api/v1/spindles/{id}/chtc``, never ``/api/v1/chtc``, which is 404 on a host);
- anything else (today's paths, ``/``): the spindle's own when the instance hosts exactly one, else a 404
  that says to use ``/api/v1/spindles/{id}/…``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.metrics_core import Metric
from starlette.types import ASGIApp, Receive, Scope, Send

from api.app import API_PREFIX, create_app
from api.deps import AuthConfig, ClockInfo, ReadAccess
from api.errors import error_body
from api.metrics import outlet_families
from api.outlet import RestOutlet

if TYPE_CHECKING:
    from service.contracts.metrics import OutletMetrics
    from service.serve.interface import FleetHost
    from service.serve.outlet import OutletContext

__all__ = ["FleetDispatch", "FleetOutlet", "create_fleet_app", "fleet_outlet"]

_SPINDLE_API = re.compile(r"^/api/v1/spindles/([^/]+)(/.*)$")
_SPINDLE_PAGE = re.compile(r"^/spindles/([^/]+)(/.*)?$")
OPENAPI_PATH = f"{API_PREFIX}/openapi.json"
_FLEET_PATHS = frozenset(
    {"/api/v1/spindles", "/api/v1/spindles/", "/metrics", "/api/v1/metrics", "/healthz", "/readyz"}
    | {"/api/v1/healthz", "/api/v1/readyz"}
)


class MergedMetrics:
    """The spindles' exposed families merged by name (a family's samples from every spindle, its HELP and
    TYPE once), so ``/metrics`` stays one valid exposition; then the host's own outlets' counters
    (``host_outlets``: the OPC UA server's and the MQTT edge node's, ``chtc_outlet_*`` without a ``spindle``
    label: one server and one node serve every spindle)."""

    def __init__(
        self,
        apps: Mapping[str, FastAPI],
        host_outlets: Callable[[], Mapping[str, OutletMetrics]] = dict,
    ) -> None:
        self.apps = apps
        self.host_outlets = host_outlets

    def collect(self) -> Iterator[Metric]:
        merged: dict[str, Metric] = {}
        families = [fam for app in self.apps.values() for fam in app.state.metrics.exposed.collect()]
        for fam in [*families, *outlet_families(self.host_outlets())]:
            out = merged.get(fam.name)
            if out is None:
                out = merged[fam.name] = Metric(fam.name, fam.documentation, fam.type, fam.unit)
            out.samples.extend(fam.samples)
        yield from merged.values()


def create_fleet_app(host: FleetHost, apps: Mapping[str, FastAPI], *, clock_info: ClockInfo) -> FastAPI:
    """The instance's own answers (list, health, readiness, metrics); no spindle's routes. The list and the
    metrics honour ``[api] read_token`` as every spindle's reads do."""
    app = FastAPI(
        title="spindle-chtc (host)",
        version="1",
        description="An instance hosting several spindles: its own answers here; each spindle's API under "
        "/api/v1/spindles/{spindle_id}/ (its document: /api/v1/spindles/{spindle_id}/openapi.json).",
        openapi_url=OPENAPI_PATH,
        docs_url=None,
        redoc_url=None,
    )
    app.state.auth = AuthConfig.from_settings(host.settings.api)
    app.state.clock_info = clock_info
    metrics = MergedMetrics(apps, host.outlet_metrics)

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
    _install_host_openapi(app)
    return app


def _install_host_openapi(app: FastAPI) -> None:
    """The instance's document: its routes, and the spindles' documents with the 404 of an unknown id."""
    from fastapi.openapi.utils import get_openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            doc = get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes
            )
            not_found = {
                "description": "no running spindle with this id on this instance (the list: /api/v1/spindles)"
            }
            doc["paths"][f"{API_PREFIX}/spindles/{{spindle_id}}/openapi.json"] = {
                "get": {
                    "summary": "The spindle's OpenAPI document (paths under /api/v1/spindles/{spindle_id}/)",
                    "parameters": [
                        {"name": "spindle_id", "in": "path", "required": True, "schema": {"type": "string"}}
                    ],
                    "responses": {"200": {"description": "the document"}, "404": not_found},
                }
            }
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def spindle_openapi(app: FastAPI, sid: str) -> dict[str, Any]:
    """``app``'s document with the paths a host serves for spindle ``sid``: ``/api/v1/x`` as
    ``/api/v1/spindles/{sid}/x``; paths outside ``/api/v1`` (reached only on a one-spindle instance) left
    out."""
    import copy

    doc = copy.deepcopy(app.openapi())
    paths = doc.get("paths", {})
    doc["paths"] = {
        f"{API_PREFIX}/spindles/{sid}{p.removeprefix(API_PREFIX)}": item
        for p, item in paths.items()
        if p == API_PREFIX or p.startswith(API_PREFIX + "/")
    }
    return doc


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
            if m.group(2) == "/openapi.json" and m.group(1) in self.apps:
                doc = spindle_openapi(self.apps[m.group(1)], m.group(1))
                await JSONResponse(doc)(scope, receive, send)
                return
            await self._to_spindle(m.group(1), API_PREFIX + m.group(2), scope, receive, send)
            return
        if m := _SPINDLE_PAGE.match(path):
            await self._to_spindle(m.group(1), m.group(2) or "/", scope, receive, send)
            return
        if path in _FLEET_PATHS or (path == OPENAPI_PATH and len(self.apps) != 1):
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
    context's ``service`` is the ``service.host.fleet.Host``."""

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
