"""Dependencies of the routers, as ``Annotated`` aliases.

- ``ServiceDep``: the :class:`service.serve.interface.ChtcService` the app was built with.
- ``SpindleIdDep``: the id of the spindle the app serves (``settings.spindle.id``), named in every answer.
- ``ClockDep``: a callable returning the current UTC ``datetime`` (injected, so tests control "now").
- ``ReadAccess`` / ``WriteAccess``: bearer-token checks. Writes need ``settings.api.token`` (401 when the
  header is missing, 403 when it is wrong or no token is configured). Reads are open unless
  ``settings.api.read_token`` is set; then either token is accepted.
"""

from __future__ import annotations

import re
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated

from fastapi import Depends, Request
from pydantic import AfterValidator, AwareDatetime, BeforeValidator

from api.errors import ApiError
from service.serve.interface import ChtcService

if TYPE_CHECKING:
    from pydantic import SecretStr

    from service.settings import ApiSettings

Clock = Callable[[], datetime]


@dataclass(frozen=True, kw_only=True)
class ClockInfo:
    """What the service's clock is: the wall clock (``simulated`` False, ``speedup`` 1), or a simulated
    plant time (``chtc demo``, ``chtc replay``) running ``speedup`` plant seconds per wall second."""

    simulated: bool = False
    speedup: float = 1.0


@dataclass(frozen=True, kw_only=True)
class AuthConfig:
    write_token: str | None
    read_token: str | None

    @classmethod
    def from_settings(cls, api_settings: ApiSettings) -> AuthConfig:
        return cls(write_token=_secret(api_settings.token), read_token=_secret(api_settings.read_token))


def _secret(value: SecretStr | None) -> str | None:
    return None if value is None else value.get_secret_value() or None


def _unauthorized(message: str) -> ApiError:
    return ApiError(
        status=401,
        code="unauthorized",
        message=message,
        field="Authorization",
        headers={"WWW-Authenticate": "Bearer"},
    )


def bearer_token(header: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header; None without one; 401 for another scheme."""
    if header is None:
        return None
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise _unauthorized("Authorization header must be 'Bearer <token>'")
    return token.strip()


def _matches(given: str, *expected: str | None) -> bool:
    return any(e is not None and secrets.compare_digest(given.encode(), e.encode()) for e in expected)


def write_denial(auth: AuthConfig, header: str | None) -> ApiError | None:
    """Why a write with this ``Authorization`` header is refused (401/403), or None when it is allowed."""
    try:
        token = bearer_token(header)
    except ApiError as err:
        return err
    if token is None:
        return _unauthorized("this endpoint needs 'Authorization: Bearer <token>'")
    if auth.write_token is None:
        return ApiError(
            status=403,
            code="forbidden",
            message="writes are disabled: no API token is configured (api.token)",
            field="Authorization",
        )
    if not _matches(token, auth.write_token):
        return ApiError(
            status=403,
            code="forbidden",
            message="the bearer token is not valid for writes",
            field="Authorization",
        )
    return None


def read_denial(auth: AuthConfig, header: str | None) -> ApiError | None:
    """Why a read with this ``Authorization`` header is refused (401/403), or None when it is allowed."""
    if auth.read_token is None:
        return None
    try:
        token = bearer_token(header)
    except ApiError as err:
        return err
    if token is None:
        return _unauthorized("reads need 'Authorization: Bearer <read token>'")
    if not _matches(token, auth.read_token, auth.write_token):
        return ApiError(
            status=403, code="forbidden", message="the bearer token is not valid", field="Authorization"
        )
    return None


async def require_write(request: Request) -> None:
    denial = write_denial(request.app.state.auth, request.headers.get("authorization"))
    if denial is not None:
        raise denial


async def require_read(request: Request) -> None:
    denial = read_denial(request.app.state.auth, request.headers.get("authorization"))
    if denial is not None:
        raise denial


async def get_service(request: Request) -> ChtcService:
    return request.app.state.service  # type: ignore[no-any-return,unused-ignore]


async def get_spindle_id(request: Request) -> str:
    return request.app.state.spindle_id  # type: ignore[no-any-return,unused-ignore]


async def get_clock(request: Request) -> Clock:
    return request.app.state.clock  # type: ignore[no-any-return,unused-ignore]


ServiceDep = Annotated[ChtcService, Depends(get_service)]
SpindleIdDep = Annotated[str, Depends(get_spindle_id)]
ClockDep = Annotated[Clock, Depends(get_clock)]
ReadAccess = Depends(require_read)
WriteAccess = Annotated[None, Depends(require_write)]


# Query date-times: ISO-8601 text only (not a Unix number), converted to UTC.
_ISO_DATE_TIME = re.compile(r"^\d{4}-\d{2}-\d{2}[Tt ]\d{2}:\d{2}")


def _iso_text(value: object) -> object:
    """Only ISO-8601 text: pydantic alone would also read ``0.5`` as a Unix time."""
    if not isinstance(value, str) or not _ISO_DATE_TIME.match(value):
        raise ValueError("must be an ISO-8601 date-time with a UTC offset, e.g. 2026-11-22T08:00:00Z")
    return value


def _in_utc(value: datetime) -> datetime:
    try:
        return value.astimezone(UTC)
    except OverflowError:
        raise ValueError("is out of range once converted to UTC") from None


UtcDateTime = Annotated[AwareDatetime, BeforeValidator(_iso_text), AfterValidator(_in_utc)]
