"""One JSON error shape for every failure the API returns.

Shape: ``{"error": {"code": str, "message": str, "field": str | None, "detail": any}}``.

Error tree (API layer)::

    ApiError(Exception)              status, code, message, field, detail; raised by routers and deps
    └── _Rejected(ApiError)          api/guard.py: refused before the app (auth, size and URL caps)

The service's errors (``service.errors.ServiceError``, the root of every error of ``service/``; the API
imports it through ``service.serve.interface``) are translated once, here:

    NotFoundError  -> 404 not_found       BusyError     -> 409 busy
    NoDataYetError -> 503 no_data         NotReadyError -> 503 not_ready (both with Retry-After)
    any other ServiceError -> 500 service_error

FastAPI's ``RequestValidationError`` becomes 422 ``invalid`` naming the first bad field (``body`` and the
character position for malformed JSON); Starlette's ``HTTPException`` (unknown route, a body over the cap or
too slow, see ``api/guard.py``) keeps its status with a code derived from it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NotRequired, TypedDict

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic_core import ErrorDetails
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.contracts.errors import BusyError, NoDataYetError, NotFoundError, NotReadyError
from service.errors import ServiceError


class ApiError(Exception):
    """An error response: HTTP status, machine code, human message, the offending field (if any)."""

    def __init__(
        self,
        *,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        detail: object = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.detail = detail
        self.headers = headers


def invalid(field: str, message: str, *, detail: object = None) -> ApiError:
    """A 422 naming the bad query/body field."""
    return ApiError(status=422, code="invalid", message=f"{field}: {message}", field=field, detail=detail)


def error_body(
    code: str, message: str, *, field: str | None = None, detail: object = None
) -> dict[str, dict[str, object]]:
    return {"error": {"code": code, "message": message, "field": field, "detail": detail}}


_SERVICE_ERRORS: tuple[tuple[type[ServiceError], int, str], ...] = (
    (NotFoundError, 404, "not_found"),
    (BusyError, 409, "busy"),
    (NoDataYetError, 503, "no_data"),
    (NotReadyError, 503, "not_ready"),
)

_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    408: "timeout",
    413: "too_large",
    414: "uri_too_long",
}


def _field_of(loc: Sequence[int | str]) -> str | None:
    parts = [str(p) for p in loc if p not in ("query", "body", "path", "header")]
    return ".".join(parts) if parts else None


async def _api_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    body = error_body(exc.code, exc.message, field=exc.field, detail=exc.detail)
    return JSONResponse(body, status_code=exc.status, headers=exc.headers)


async def _service_error(_: Request, exc: Exception) -> JSONResponse:
    for cls, status, code in _SERVICE_ERRORS:
        if isinstance(exc, cls):
            headers = {"Retry-After": "5"} if status == 503 else None
            return JSONResponse(error_body(code, str(exc)), status_code=status, headers=headers)
    return JSONResponse(error_body("service_error", str(exc)), status_code=500)


class _Problem(TypedDict):
    field: str | None
    message: str
    type: NotRequired[str]


def _validation_item(e: ErrorDetails) -> _Problem:
    if e["type"] == "json_invalid":  # loc is ("body", <character position>): name the body and the place
        pos = e["loc"][-1] if len(e["loc"]) > 1 else None
        reason = (e.get("ctx") or {}).get("error", "not valid JSON")
        return {"field": "body", "message": f"invalid JSON at character {pos}: {reason}", "type": e["type"]}
    return {"field": _field_of(e["loc"]), "message": e["msg"], "type": e["type"]}


async def _validation_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [_validation_item(e) for e in exc.errors()]
    first: _Problem = errors[0] if errors else {"field": None, "message": "invalid request"}
    message = f"{first['field']}: {first['message']}" if first["field"] else str(first["message"])
    return JSONResponse(error_body("invalid", message, field=first["field"], detail=errors), status_code=422)


async def _http_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
    return JSONResponse(error_body(code, str(exc.detail)), status_code=exc.status_code, headers=exc.headers)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
