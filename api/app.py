"""``create_app(settings, service) -> FastAPI``: the REST API under ``/api/v1`` and the dashboard at ``/``.

``/healthz`` and ``/readyz`` answer at the root too (the same as ``/api/v1/healthz`` and ``/api/v1/readyz``).

The app reads the service only through :class:`service.serve.interface.ChtcService`. ``settings`` is the
service's ``Settings``; only ``settings.api`` (``token``, ``read_token``) and ``settings.spindle.id`` are
read. Every answer names its spindle: a ``spindle_id`` member of the top-level JSON of the read endpoints and
a ``Chtc-Spindle-Id`` header on every answer (``api/spindlehdr.py``). Binding (``api.host``/``api.port``,
127.0.0.1 by default) is the caller's job (``chtc run`` / ``chtc demo`` run uvicorn with them).
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from api.deps import AuthConfig, Clock, ClockInfo
from api.errors import install_error_handlers
from api.guard import GuardLimits, RequestGuard, RouteRule, route_rules
from api.metrics import ApiMetrics, RequestTimer
from api.openapi import build_openapi
from api.routers import (
    chtc,
    chtc_map,
    compensation,
    condition,
    field,
    health,
    history,
    identifications,
    sensors,
    spindle,
)
from api.spindlehdr import SpindleHeader
from service.serve.interface import ChtcService

if TYPE_CHECKING:
    from service.settings import Settings

API_PREFIX = "/api/v1"
STATIC_DIR = Path(__file__).parent / "static"
# The page may load and fetch only from its own origin (no CDN, no third-party beacons).
DASHBOARD_HEADERS = {
    "Cache-Control": "no-cache",
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' data:; object-src 'none'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


def utc_now() -> datetime:
    return datetime.now(UTC)


def create_app(
    settings: Settings,
    service: ChtcService,
    *,
    clock: Clock = utc_now,
    limits: GuardLimits | None = None,
    clock_info: ClockInfo | None = None,
) -> FastAPI:
    """Build the app around an already running service; nothing is opened here.

    ``limits`` bounds bodies, URLs and slow bodies (``api/guard.py``); the defaults suit this API.
    ``clock_info`` says whether ``clock`` is a simulated plant time (``/healthz``'s ``clock``; the dashboard
    marks its times as such); default: the wall clock.
    """
    limits = limits or GuardLimits()
    app = FastAPI(
        title="spindle-chtc",
        version="1",
        description="Online soft sensor for spindle convective heat transfer coefficients H1-H7.",
        openapi_url=f"{API_PREFIX}/openapi.json",
        docs_url=None,  # Swagger UI would load from a CDN; the shop floor is offline
        redoc_url=None,
    )
    app.state.service = service
    app.state.spindle_id = settings.spindle.id
    app.state.clock = clock
    app.state.clock_info = clock_info or ClockInfo()
    app.state.auth = AuthConfig.from_settings(settings.api)
    app.state.metrics = ApiMetrics(service, spindle_id=settings.spindle.id)
    install_error_handlers(app)
    modules = (
        chtc,
        chtc_map,
        compensation,
        field,
        sensors,
        history,
        spindle,
        condition,
        identifications,
        health,
    )
    for module in modules:
        app.include_router(module.router, prefix=API_PREFIX)
    app.include_router(health.probes)  # /healthz and /readyz at the root too, for probes
    _mount_dashboard(app)
    rules = route_rules((r for m in modules for r in m.router.routes), API_PREFIX)
    app.state.guard_rules = rules
    probe_rules = route_rules(health.probes.routes, "")
    app.add_middleware(RequestGuard, rules=[*rules, *probe_rules], auth=app.state.auth, limits=limits)
    _install_openapi(app, rules)
    app.add_middleware(RequestTimer, metrics=app.state.metrics, prefix=API_PREFIX)
    app.add_middleware(SpindleHeader, spindle_id=settings.spindle.id)  # outermost: on every answer
    return app


def _install_openapi(app: FastAPI, rules: list[RouteRule]) -> None:
    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = build_openapi(app, rules=rules, auth=app.state.auth, prefix=API_PREFIX)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def _mount_dashboard(app: FastAPI) -> None:
    index = STATIC_DIR / "index.html"

    @app.get("/", include_in_schema=False)
    async def dashboard() -> FileResponse:
        return FileResponse(index, headers=DASHBOARD_HEADERS)

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
