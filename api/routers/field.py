"""GET /temperature-field: the predicted temperature field on the (r, z) section.

``format=mesh`` returns the P1 mesh (nodes, triangles, nodal °C); ``format=grid`` samples it on a regular
``nr`` x ``nz`` grid over the section's bounding box (null outside the section); ``format=points``
evaluates it at ``points=r1,z1;r2,z2;...`` (m). Sizes are bounded so one request cannot monopolise the CPU.

The work runs in a worker thread, never on the event loop; mesh and grid bodies are cached per field content
with an ETag (304 when unchanged) and sent gzip-compressed when the client accepts it
(``api.routers.field_render``). At most ``MAX_IN_PROGRESS`` field requests are served at once; the next gets a
503 ``overloaded`` with ``Retry-After: 1`` at once, so a burst of field requests never queues up in front of
``/chtc``.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from api.deps import ReadAccess, ServiceDep
from api.errors import ApiError, invalid
from api.routers.conditional import if_none_match
from api.routers.field_render import GZIP_MIN_BYTES, FieldGate, FieldRenderer, Rendered, _clean
from api.schemas import FieldGridOut, FieldMeshOut, FieldPointsOut, PointOut
from api.stdmax import std_max
from service.contracts.snapshots import FieldAt, FieldSnapshot
from service.serve.interface import ChtcService

router = APIRouter(tags=["temperature field"], dependencies=[ReadAccess])

MAX_GRID = 200
MAX_POINTS = 1000
MAX_POINTS_CHARS = 20_000  # 1000 pairs of 9-digit numbers
# 'r1,z1;r2,z2;...' in m; bounded digits and exponents keep every number finite
_NUMBER = r"[+-]?(?:[0-9]{1,15}(?:\.[0-9]{0,15})?|\.[0-9]{1,15})(?:[eE][+-]?[0-9]{1,2})?"
POINTS_PATTERN = rf"^{_NUMBER},{_NUMBER}(?:;{_NUMBER},{_NUMBER})*;?$"
MAX_IN_PROGRESS = 4  # field requests being served at once; more get a 503 with Retry-After (load shedding)


def parse_points(text: str) -> np.ndarray:
    """``"r1,z1;r2,z2"`` (m) -> (P, 2); raises a 422 naming ``points`` and the bad pair."""
    pairs = [p for p in text.replace(" ", "").split(";") if p]
    if not pairs:
        raise invalid("points", "no points given; expected 'r1,z1;r2,z2;...' in m")
    if len(pairs) > MAX_POINTS:
        raise invalid("points", f"{len(pairs)} points given, at most {MAX_POINTS} allowed")
    out = np.empty((len(pairs), 2))
    for i, pair in enumerate(pairs):
        parts = pair.split(",")
        try:
            if len(parts) != 2:
                raise ValueError
            out[i] = [float(parts[0]), float(parts[1])]
        except ValueError:
            raise invalid("points", f"pair {i + 1} ({pair!r}) is not 'r,z' with two numbers in m") from None
        if not all(math.isfinite(v) for v in out[i]):
            raise invalid("points", f"pair {i + 1} ({pair!r}) is not finite")
    return out


def _meta(f: FieldSnapshot, spindle_id: str) -> dict[str, object]:
    finite = f.temps_c[np.isfinite(f.temps_c)]
    return {
        "spindle_id": spindle_id,
        "at": f.at,
        "t": f.t,
        "identification_id": f.identification_id,
        "t_min_c": round(float(finite.min()), 4) if finite.size else None,
        "t_max_c": round(float(finite.max()), 4) if finite.size else None,
        "std_max_c": std_max(f),
    }


# mesh_out / grid_out: the schema-level forms of the bodies. The route serves field_render's cached bodies,
# which must parse to exactly these (tests/api/test_api_field.py compares them).
def mesh_out(f: FieldSnapshot, *, spindle_id: str) -> FieldMeshOut:
    return FieldMeshOut(
        **_meta(f, spindle_id),  # type: ignore[arg-type]
        nodes_r_m=np.round(f.nodes_rz[:, 0], 7).tolist(),
        nodes_z_m=np.round(f.nodes_rz[:, 1], 7).tolist(),
        temps_c=_clean(f.temps_c),
        std_c=None if f.std_c is None else _clean(f.std_c),
        triangles=np.asarray(f.triangles, dtype=int).tolist(),
    )


def grid_out(f: FieldSnapshot, nr: int, nz: int, *, spindle_id: str) -> FieldGridOut:
    r0, r1, z0, z1 = f.bounds_rz
    r = np.linspace(r0, r1, nr)
    z = np.linspace(z0, z1, nz)
    rr, zz = np.meshgrid(r, z, indexing="ij")
    pts = np.c_[rr.ravel(), zz.ravel()]
    temps = f.evaluate(pts).reshape(nr, nz)
    std = f.evaluate_std(pts)
    return FieldGridOut(
        **_meta(f, spindle_id),  # type: ignore[arg-type]
        r_m=np.round(r, 7).tolist(),
        z_m=np.round(z, 7).tolist(),
        temps_c=[_clean(row) for row in temps],
        std_c=None if std is None else [_clean(row) for row in std.reshape(nr, nz)],
    )


def points_out(f: FieldSnapshot, pts: np.ndarray, *, spindle_id: str) -> FieldPointsOut:
    temps = f.evaluate(pts)
    std = f.evaluate_std(pts)
    stds = [math.nan] * len(temps) if std is None else std.tolist()
    return FieldPointsOut(
        **_meta(f, spindle_id),  # type: ignore[arg-type]
        points=[
            _point(float(r), float(z), float(t), float(s))
            for (r, z), t, s in zip(pts, temps, stds, strict=True)
        ],
    )


def _point(r: float, z: float, t: float, s: float) -> PointOut:
    inside, known = math.isfinite(t), math.isfinite(t) and math.isfinite(s)
    return PointOut(
        r_m=r,
        z_m=z,
        temp_c=round(t, 4) if inside else None,
        inside=inside,
        std_c=round(s, 4) if known else None,
        ci95_c=(round(t - 1.96 * s, 4), round(t + 1.96 * s, 4)) if known else None,
    )


def _renderer(request: Request) -> tuple[FieldRenderer, FieldGate]:
    state = request.app.state
    if getattr(state, "field_renderer", None) is None:
        state.field_renderer = FieldRenderer(spindle_id=state.spindle_id)
        state.field_gate = FieldGate(MAX_IN_PROGRESS)
    return state.field_renderer, state.field_gate


def _accepts_gzip(request: Request) -> bool:
    for part in request.headers.get("accept-encoding", "").split(","):
        coding, _, params = part.strip().partition(";")
        if coding.strip().lower() == "gzip" and params.replace(" ", "") not in ("q=0", "q=0.0"):
            return True
    return False


def _render(
    service: ChtcService,
    renderer: FieldRenderer,
    *,
    at: FieldAt,
    format: str,
    nr: int,
    nz: int,
    pts: np.ndarray | None,
) -> Rendered | bytes:
    """The body (a worker thread runs this: reading the service may wait for its lock, and a new field's
    body is serialised here)."""
    snap = service.field(at)
    if format == "mesh":
        return renderer.mesh(snap)
    if format == "grid":
        return renderer.grid(snap, nr, nz)
    assert pts is not None  # format=points requires them (checked in get_field)
    return points_out(snap, pts, spindle_id=renderer.spindle_id).model_dump_json().encode()


@router.get(
    "/temperature-field",
    response_model=FieldMeshOut | FieldGridOut | FieldPointsOut,
    responses={
        304: {"description": "not modified since the ETag (mesh and grid)"},
        422: {
            "description": "a bad parameter, `points` without `format=points`, or `format=points` without "
            "`points` (the message names it)"
        },
        503: {"description": "no field yet, or too many field requests in progress (Retry-After)"},
    },
    summary="predicted temperature field (°C) on the (r, z) section: mesh, grid or points",
)
async def get_field(
    request: Request,
    service: ServiceDep,
    at: Annotated[Literal["now", "steady"], Query(description="current state or steady state")] = "now",
    format: Annotated[Literal["mesh", "grid", "points"], Query(description="response layout")] = "mesh",
    nr: Annotated[int, Query(ge=2, le=MAX_GRID, description="grid points along r (format=grid)")] = 60,
    nz: Annotated[int, Query(ge=2, le=MAX_GRID, description="grid points along z (format=grid)")] = 120,
    points: Annotated[
        str | None,
        Query(
            max_length=MAX_POINTS_CHARS,
            pattern=POINTS_PATTERN,
            description="'r1,z1;r2,z2' in m; required with format=points, refused (422) otherwise",
        ),
    ] = None,
) -> Response:
    pts = None
    if format == "points":
        if points is None:
            raise invalid("points", "required with format=points, e.g. points=0.03,0.1;0.08,0.2")
        pts = parse_points(points)
    elif points is not None:
        raise invalid("points", "only allowed with format=points")
    renderer, gate = _renderer(request)
    if not gate.try_enter():
        raise ApiError(
            status=503,
            code="overloaded",
            message=f"{gate.limit} temperature-field requests are in progress; retry in a second",
            headers={"Retry-After": "1"},
        )
    try:
        out = await run_in_threadpool(_render, service, renderer, at=at, format=format, nr=nr, nz=nz, pts=pts)
        if isinstance(out, bytes):
            return Response(out, media_type="application/json")
        headers = {"ETag": out.etag, "Cache-Control": "no-cache", "Vary": "Accept-Encoding"}
        if if_none_match(request.headers.get("if-none-match"), out.etag):
            return Response(status_code=304, headers=headers)
        body = out.body
        if len(body) >= GZIP_MIN_BYTES and _accepts_gzip(request):
            body = await run_in_threadpool(out.gzip)
            headers["Content-Encoding"] = "gzip"
        return Response(body, media_type="application/json", headers=headers)
    finally:
        gate.leave()
