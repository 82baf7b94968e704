"""The OpenAPI document as the API really answers: every error in the ``{"error": ...}`` shape.

FastAPI's generated document describes 422 in its own validation shape and knows nothing of the request
guard (``api/guard.py``) or the service errors. ``build_openapi`` starts from the generated document and,
per operation, documents the statuses it can answer with the ``Error`` schema: 401/403 with the bearer
scheme where the route's token rule applies (reads only when ``api.read_token`` is set), 400/408/413 where
a body is read, 404 for ids, 409 busy, 414 for an over-long URL, 422 where there are inputs, 503 with
``Retry-After`` where the service may have nothing to show or the database is down. A method a path does
not have answers 405 with ``Allow`` (stated in the description: OpenAPI cannot list undeclared methods).
Every response documents the ``Chtc-Spindle-Id`` header (``api/spindlehdr.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel, Field

from api.deps import AuthConfig
from api.guard import RouteRule
from api.spindlehdr import HEADER as SPINDLE_HEADER

BEARER = "bearerAuth"
ERROR_REF = {"$ref": "#/components/schemas/Error"}
METHOD_NOTE = (
    '\n\nEvery error answers `{"error": {"code", "message", "field", "detail"}}`. A method a path does '
    "not declare answers 405 `method_not_allowed` with an `Allow` header; every GET path also answers HEAD."
    f" Every answer names its spindle in a `{SPINDLE_HEADER}` header, and the JSON answers of the read"
    " endpoints in a top-level `spindle_id` (settings `spindle.id`)."
)
SPINDLE_HEADER_DOC = {
    "schema": {"type": "string"},
    "description": "the id of the spindle that answers (settings spindle.id)",
}
_DESCRIPTIONS = {
    "400": "the body cannot be read",
    "401": "no or malformed `Authorization: Bearer` header",
    "403": "wrong token, or writes disabled (no api.token)",
    "404": "unknown id",
    "408": "the body stalled",
    "409": "not possible now: an identification is already queued or running, or no baseline at rest",
    "413": "body larger than the cap",
    "414": "request target (path + query) too long",
    "422": "invalid input; `field` names it",
    "503": "nothing to show yet, not ready, or the database unavailable",
}
# operations that answer no 503 (liveness and the scrape endpoint never call into a failing part)
_NO_503 = {"/healthz", "/metrics"}
# 404 for an unknown id, and /chtc/map in per-condition mode (no map at all)
_NOT_FOUND = {"/identifications/{identification_id}", "/identifications/jobs/{job_id}", "/chtc/map"}


class ErrorBody(BaseModel):
    code: str = Field(description="machine-readable, e.g. invalid, unauthorized, not_found, busy, no_data")
    message: str = Field(description="human-readable; starts with the field when one is named")
    field: str | None = Field(description="the offending query/path/body field or header, if any")
    detail: object = Field(description="more about the error, e.g. every validation problem")


class Error(BaseModel):
    error: ErrorBody


def build_openapi(
    app: FastAPI, *, rules: Sequence[RouteRule], auth: AuthConfig, prefix: str
) -> dict[str, Any]:
    doc = get_openapi(
        title=app.title, version=app.version, description=app.description + METHOD_NOTE, routes=app.routes
    )
    components = doc.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    error_schema = Error.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(error_schema.pop("$defs", {}))
    schemas["Error"] = error_schema
    components["securitySchemes"] = {BEARER: {"type": "http", "scheme": "bearer"}}
    access = {(r.path, m): r.access for r in rules for m in r.methods}
    for path, operations in doc["paths"].items():
        for method, op in operations.items():
            rule = access.get((path, method.upper()), "open")
            _document(op, path.removeprefix(prefix), rule, auth)
    return doc


def _document(op: dict[str, Any], path: str, access: str, auth: AuthConfig) -> None:
    codes = ["414"]
    if access == "write" or (access == "read" and auth.read_token is not None):
        op["security"] = [{BEARER: []}]
        codes += ["401", "403"]
    if "requestBody" in op:
        codes += ["400", "408", "413"]
    if op.get("parameters") or "requestBody" in op:
        codes.append("422")
    if path in _NOT_FOUND:
        codes.append("404")
    if access == "write":
        codes.append("409")
    if path not in _NO_503:
        codes.append("503")
    responses = op.setdefault("responses", {})
    for code in codes:
        entry = responses.setdefault(code, {"description": _DESCRIPTIONS[code]})
        entry["content"] = {"application/json": {"schema": ERROR_REF}}
        headers = _error_headers(code)
        if headers:
            entry["headers"] = headers
    for code, entry in responses.items():  # a route's own error statuses (e.g. a 404) get the shape too
        if code.isdigit() and int(code) >= 400:
            entry["content"] = {"application/json": {"schema": ERROR_REF}}
        entry.setdefault("headers", {})[SPINDLE_HEADER] = SPINDLE_HEADER_DOC
    if path == "/metrics":
        responses["200"]["content"] = {"text/plain": {"schema": {"type": "string"}}}


def _error_headers(code: str) -> dict[str, dict[str, object]]:
    if code == "401":
        return {"WWW-Authenticate": {"schema": {"type": "string"}, "description": "Bearer"}}
    if code == "503":
        return {"Retry-After": {"schema": {"type": "string"}, "description": "seconds"}}
    return {}
