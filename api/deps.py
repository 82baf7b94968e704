"""Dependencies of the routers, as ``Annotated`` aliases.

- ``ServiceDep``: the :class:`service.interface.ChtcService` the app was built with.
- ``ClockDep``: a callable returning the current UTC ``datetime`` (injected, so tests control "now").
- ``ReadAccess`` / ``WriteAccess``: bearer-token checks. Writes need ``settings.api.token`` (401 when the
  header is missing, 403 when it is wrong or no token is configured). Reads are open unless
  ``settings.api.read_token`` is set; then either token is accepted.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any

from fastapi import Depends, Request

from api.errors import ApiError
from service.interface import ChtcService

Clock = Callable[[], datetime]


@dataclass(frozen=True)
class AuthConfig:
    write_token: str | None
    read_token: str | None

    @classmethod
    def from_settings(cls, api_settings: Any) -> AuthConfig:
        return cls(
            _secret(getattr(api_settings, "token", None)), _secret(getattr(api_settings, "read_token", None))
        )


def _secret(value: Any) -> str | None:
    if value is None:
        return None
    text = value.get_secret_value() if hasattr(value, "get_secret_value") else str(value)
    return text or None


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization")
    if header is None:
        return None
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise ApiError(
            401,
            "unauthorized",
            "Authorization header must be 'Bearer <token>'",
            field="Authorization",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return token.strip()


def _matches(given: str, *expected: str | None) -> bool:
    return any(e is not None and secrets.compare_digest(given.encode(), e.encode()) for e in expected)


async def require_write(request: Request) -> None:
    auth: AuthConfig = request.app.state.auth
    token = _bearer(request)
    if token is None:
        raise ApiError(
            401,
            "unauthorized",
            "this endpoint needs 'Authorization: Bearer <token>'",
            field="Authorization",
            headers={"WWW-Authenticate": "Bearer"},
        )
    if auth.write_token is None:
        raise ApiError(
            403,
            "forbidden",
            "writes are disabled: no API token is configured (api.token)",
            field="Authorization",
        )
    if not _matches(token, auth.write_token):
        raise ApiError(403, "forbidden", "the bearer token is not valid for writes", field="Authorization")


async def require_read(request: Request) -> None:
    auth: AuthConfig = request.app.state.auth
    if auth.read_token is None:
        return
    token = _bearer(request)
    if token is None:
        raise ApiError(
            401,
            "unauthorized",
            "reads need 'Authorization: Bearer <read token>'",
            field="Authorization",
            headers={"WWW-Authenticate": "Bearer"},
        )
    if not _matches(token, auth.read_token, auth.write_token):
        raise ApiError(403, "forbidden", "the bearer token is not valid", field="Authorization")


async def get_service(request: Request) -> ChtcService:
    return request.app.state.service  # type: ignore[no-any-return,unused-ignore]


async def get_clock(request: Request) -> Clock:
    return request.app.state.clock  # type: ignore[no-any-return,unused-ignore]


ServiceDep = Annotated[ChtcService, Depends(get_service)]
ClockDep = Annotated[Clock, Depends(get_clock)]
ReadAccess = Depends(require_read)
WriteAccess = Annotated[None, Depends(require_write)]
