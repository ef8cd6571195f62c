"""HEAD answered as GET without the body (RFC 9110 9.3.2), for every route.

FastAPI's routes answer only the methods they declare, so a GET route met HEAD with 405
(uptime checkers and load balancers probe with HEAD). This middleware hands a HEAD request
to the application as a GET — the same key checks, the same status and headers, including the
Content-Length the GET would have — and sends none of the body.
"""
from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class HeadAsGet:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def without_body(message: Message) -> None:
            if message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, without_body)


__all__ = ["HeadAsGet"]
