"""Liveness, readiness and Prometheus metrics.

healthz/readyz are open to probes; metrics honour the read token. ``probes`` serves the same two answers
at the root (``/healthz``, ``/readyz``), where many deployments' probes look; they are not in the OpenAPI
document (the ``/api/v1`` ones are).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from api.deps import ClockDep, ReadAccess, ServiceDep, SpindleIdDep
from api.errors import error_body
from api.schemas import HealthOut, ReadyOut, health_out

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=HealthOut, summary="liveness plus device health (always 200 if alive)")
async def healthz(service: ServiceDep, request: Request, spindle_id: SpindleIdDep) -> HealthOut:
    return health_out(service.health(), request.app.state.clock_info, spindle_id=spindle_id)


@router.get(
    "/readyz",
    response_model=ReadyOut,
    responses={503: {"description": "model not loaded or data not fresh"}},
    summary="ready = model loaded and data fresh",
)
async def readyz(service: ServiceDep, clock: ClockDep, spindle_id: SpindleIdDep) -> JSONResponse:
    r = service.ready()
    body = ReadyOut(spindle_id=spindle_id, ready=r.ready, reasons=list(r.reasons), t=clock())
    if r.ready:
        return JSONResponse(body.model_dump(mode="json"))
    msg = "not ready: " + "; ".join(r.reasons) if r.reasons else "not ready"
    return JSONResponse(
        error_body("not_ready", msg, detail=body.model_dump(mode="json")),
        status_code=503,
        headers={"Retry-After": "5"},
    )


@router.get(
    "/metrics", dependencies=[ReadAccess], summary="Prometheus text exposition", response_class=Response
)
def metrics(request: Request) -> Response:
    data = generate_latest(request.app.state.metrics.exposed)
    return Response(data, media_type=CONTENT_TYPE_LATEST)


probes = APIRouter(include_in_schema=False)
probes.add_api_route("/healthz", healthz, methods=["GET"], response_model=HealthOut)
probes.add_api_route("/readyz", readyz, methods=["GET"], response_model=ReadyOut)
