"""``SpindleHeader``: every HTTP answer names its spindle in a ``Chtc-Spindle-Id`` header (pure ASGI).

The outermost middleware of the app (``api/app.py``), so the guard's refusals, 404s, the dashboard, static
files and the OpenAPI document carry it too. It also runs the request as that spindle
(``service.logctx.spindle_context``): a log line written while answering names the spindle.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.logctx import spindle_context

HEADER = "Chtc-Spindle-Id"


class SpindleHeader:
    def __init__(self, app: ASGIApp, *, spindle_id: str) -> None:
        self.app = app
        self.spindle_id = spindle_id
        self._header = (HEADER.lower().encode("latin-1"), spindle_id.encode("latin-1"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_header(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), self._header]}
            await send(message)

        with spindle_context(self.spindle_id):
            await self.app(scope, receive, send_with_header)
