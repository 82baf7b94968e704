"""``RequestGuard``: checks every HTTP request passes before a route reads its body (pure ASGI middleware).

FastAPI reads and parses a request body before it runs the route's dependencies, so a bearer-token check
written as a dependency comes too late: a 200 MB body without a token would be read, and malformed JSON
without a token would be a 422 instead of a 401. The guard runs first, in this order:

1. a request target (path + query) longer than ``max_url_bytes`` -> 414 ``uri_too_long``;
2. the route: a path the API knows with a method it does not -> 405 with ``Allow`` listing every method of
   that path (``HEAD`` is answered for every GET route: the GET's status and headers without the body);
3. the route's bearer-token rule (taken from its ``require_write`` / ``require_read`` dependency) -> 401/403;
4. ``Content-Length`` above ``max_body_bytes`` -> 413 ``too_large`` (``large_body_bytes`` for the write
   routes in ``large_body_routes``: a thermal test's files, ``POST /compensation/mechanics``, only after the
   token was checked).

Each of these answers in the error shape with ``Connection: close`` and without reading the body. While a
route reads its body the guard counts the bytes (413 once a chunked body exceeds the cap) and gives each
chunk ``body_timeout_s`` (408 ``timeout`` for a client that stops sending). An exception a route lets escape
becomes a 500 ``internal`` in the error shape and one log line (the traceback only at DEBUG level).
Paths the guard does not know (dashboard, static files, the OpenAPI document, unknown paths) pass through.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException
from starlette.routing import BaseRoute, compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.deps import AuthConfig, read_denial, require_read, require_write, write_denial
from api.errors import ApiError, error_body

log = logging.getLogger("api")

Access = Literal["open", "read", "write"]


@dataclass(frozen=True, kw_only=True)
class GuardLimits:
    max_body_bytes: int = 4096  # the largest legitimate body is {"reason": "<= 64 chars"}
    max_url_bytes: int = 64 * 1024  # format=points takes up to 20 000 characters (percent-encoded: more)
    body_timeout_s: float = 10.0  # per received chunk of a body
    # write routes that take files: a 4-h thermal test at 1 Hz is ~15 MB of CSV and CAN log (base64)
    large_body_routes: tuple[str, ...] = ("/compensation/mechanics",)
    large_body_bytes: int = 96 * 1024 * 1024


@dataclass(frozen=True, kw_only=True)
class RouteRule:
    path: str  # the template, e.g. /api/v1/identifications/{identification_id}
    pattern: re.Pattern[str]
    methods: frozenset[str]
    access: Access


def _calls(dependant: Dependant) -> Iterator[object]:
    for dep in dependant.dependencies:
        yield dep.call
        yield from _calls(dep)


def route_access(route: APIRoute) -> Access:
    """The bearer-token rule of a route, read from its dependencies (one source of truth)."""
    calls = set(_calls(route.dependant))
    if require_write in calls:
        return "write"
    return "read" if require_read in calls else "open"


def route_rules(routes: Iterable[BaseRoute], prefix: str) -> list[RouteRule]:
    """One rule per API route, in the order the app tries them."""
    return [
        RouteRule(
            path=prefix + r.path,
            pattern=compile_path(prefix + r.path)[0],
            methods=frozenset(r.methods or ()),
            access=route_access(r),
        )
        for r in routes
        if isinstance(r, APIRoute)
    ]


def allowed_methods(rules: Sequence[RouteRule]) -> list[str]:
    methods = set().union(*(r.methods for r in rules))
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods)


class _Rejected(ApiError):
    """A request the guard refuses before the app sees it; ``error`` is the answer it gets."""

    def __init__(self, error: ApiError) -> None:
        super().__init__(
            status=error.status,
            code=error.code,
            message=error.message,
            field=error.field,
            detail=error.detail,
            headers=error.headers,
        )
        self.error = error


class RequestGuard:
    def __init__(
        self,
        app: ASGIApp,
        *,
        rules: Sequence[RouteRule],
        auth: AuthConfig,
        limits: GuardLimits,
    ) -> None:
        self.app = app
        self.rules = tuple(rules)
        self.auth = auth
        self.limits = limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = [False]

        async def tracking_send(message: Message) -> None:
            started[0] = started[0] or message["type"] == "http.response.start"
            await send(message)

        try:
            scope, send_on, cap = self._admit(scope, tracking_send)
            await self.app(scope, self._counting(receive, cap), send_on)
        except _Rejected as rej:
            if not started[0]:
                await _send_error(tracking_send, rej.error, close=True)
        except Exception as err:  # the one place that turns a bug into a 500 in the error shape
            log.error("%s %s: unhandled %s: %s", scope["method"], scope["path"], type(err).__name__, err)
            log.debug("traceback", exc_info=True)
            if not started[0]:
                message = f"internal error ({type(err).__name__}); see the service log"
                await _send_error(
                    tracking_send, ApiError(status=500, code="internal", message=message), close=True
                )

    def _admit(self, scope: Scope, send: Send) -> tuple[Scope, Send, int]:
        """Raise :class:`_Rejected` for the checks 1-4; return the scope and send to run the app with, and the
        body cap of its route."""
        target = len(scope.get("raw_path") or scope["path"].encode()) + len(scope.get("query_string", b""))
        if target > self.limits.max_url_bytes:
            raise _Rejected(
                ApiError(
                    status=414,
                    code="uri_too_long",
                    message=f"request target is {target} bytes, at most {self.limits.max_url_bytes} allowed",
                )
            )
        candidates = [r for r in self.rules if r.pattern.match(scope["path"])]
        if not candidates:
            return scope, send, self.limits.max_body_bytes
        method = scope["method"]
        head = method == "HEAD" and not any("HEAD" in r.methods for r in candidates)
        wanted = "GET" if head else method
        rule = next((r for r in candidates if wanted in r.methods), None)
        if rule is None:
            allow = ", ".join(allowed_methods(candidates))
            raise _Rejected(
                ApiError(
                    status=405,
                    code="method_not_allowed",
                    message=f"{method} is not allowed here; allowed: {allow}",
                    headers={"Allow": allow},
                )
            )
        self._authorize(rule.access, scope)
        large = rule.access == "write" and any(rule.path.endswith(r) for r in self.limits.large_body_routes)
        cap = self.limits.large_body_bytes if large else self.limits.max_body_bytes
        self._check_length(scope, cap)
        if head:
            return {**scope, "method": "GET"}, _without_body(send), cap
        return scope, send, cap

    def _authorize(self, access: Access, scope: Scope) -> None:
        if access == "open":
            return
        header = _header(scope, b"authorization")
        denial = write_denial(self.auth, header) if access == "write" else read_denial(self.auth, header)
        if denial is not None:
            raise _Rejected(denial)

    def _check_length(self, scope: Scope, cap: int) -> None:
        length = _header(scope, b"content-length")
        if length is not None and length.strip().isdigit() and int(length) > cap:
            raise _Rejected(self._too_large(int(length), cap))

    @staticmethod
    def _too_large(size: int, cap: int) -> ApiError:
        return ApiError(
            status=413,
            code="too_large",
            message=f"request body is {size} bytes or more, at most {cap} allowed",
        )

    def _counting(self, receive: Receive, cap: int) -> Receive:
        """``receive`` with the body cap and the per-chunk timeout applied while a body is being read."""
        state = {"received": 0, "done": False}

        async def guarded() -> Message:
            if state["done"]:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.limits.body_timeout_s)
            except TimeoutError:
                raise HTTPException(
                    408, f"no request body data for {self.limits.body_timeout_s:g} s", {"Connection": "close"}
                ) from None
            if message["type"] == "http.request":
                state["received"] += len(message.get("body", b""))
                if state["received"] > cap:
                    err = self._too_large(state["received"], cap)
                    raise HTTPException(413, err.message, {"Connection": "close"})
                state["done"] = not message.get("more_body", False)
            else:
                state["done"] = True
            return message

        return guarded


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return bytes(value).decode("latin-1")
    return None


def _without_body(send: Send) -> Send:
    async def head_send(message: Message) -> None:
        if message["type"] == "http.response.body":
            message = {**message, "body": b""}
        await send(message)

    return head_send


async def _send_error(send: Send, error: ApiError, *, close: bool) -> None:
    body = json.dumps(error_body(error.code, error.message, field=error.field, detail=error.detail)).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in (error.headers or {}).items()]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": error.status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
