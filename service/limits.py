"""Request limits: body size (413 problem, on Content-Length and on the bytes sent) and requests in flight (503)."""
from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.problems import PAYLOAD_TOO_LARGE, SERVER_BUSY, ApiProblem, problem_response


class BodySizeLimit:
    """Refuses bodies over ``max_bytes``: declared ones at once, chunked ones as they arrive.

    ``larger``: paths allowed a larger limit of their own (the ingest of gateways' batches).
    """

    def __init__(self, app: ASGIApp, max_bytes: int, larger: dict[str, int] | None = None) -> None:
        self.app = app
        self.default_max_bytes = max_bytes
        self.larger = dict(larger or {})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        max_bytes = self.larger.get(scope["path"], self.default_max_bytes)
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None:
            try:
                too_large = int(declared) > max_bytes
            except ValueError:
                too_large = False  # the server rejects a malformed Content-Length itself
            if too_large:
                response = problem_response(PAYLOAD_TOO_LARGE, f"the request body exceeds {max_bytes} bytes", None)
                await response(scope, receive, send)
                return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > max_bytes:
                    raise ApiProblem(PAYLOAD_TOO_LARGE, f"the request body exceeds {max_bytes} bytes")
            return message

        await self.app(scope, limited_receive, send)


class RequestsInFlightLimit:
    """At most ``max_requests`` requests in the application at once; the next get a 503 problem.

    The overload guard uvicorn's ``limit_concurrency`` was, counting requests being handled only:
    uvicorn's counts open connections too, so idle or half-open ones (slowloris) made every
    request a 503 (service/connection_guard.py bounds those instead).
    """

    def __init__(self, app: ASGIApp, max_requests: int) -> None:
        self.app = app
        self.max_requests = max_requests
        self.in_flight = 0  # one event loop: no lock needed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if self.in_flight >= self.max_requests:
            response = problem_response(SERVER_BUSY, f"more than {self.max_requests} requests in progress; retry",
                                        None, headers={"Retry-After": "1"})
            await response(scope, receive, send)
            return
        self.in_flight += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= 1
