"""Slow and idle clients cannot take the server's connections: a deadline per request, a cap on waiting ones.

uvicorn bounds nothing while a request arrives: its keep-alive timer is reset by every byte
received, so a client sending one header line and then nothing (slowloris) holds its
connection for ever, and with ``limit_concurrency`` every such connection counts against the
limit until the server answers 503 to everyone (uvicorn issue #157: ``--timeout-request-start``
is still open). ASGI middleware cannot help: it runs only once the head has arrived.

:class:`GuardedHttpProtocol` is uvicorn's httptools protocol with two additions at the socket layer:

* **a request deadline**: from the moment a connection opens (or its previous response was
  sent) the whole request, head and body, must arrive within ``request_timeout_s``; if not, the
  server answers ``408`` (when no request is in progress) and closes the connection;
* **a cap on open connections**: when a new connection would exceed ``max_connections``, the one
  that has waited longest for its request is closed; a client that sends its request at once is
  never the one waiting longest, so it is served however many half-open connections exist.

Requests are never cut off once read: the application's time is not bounded here.
"""
from __future__ import annotations

import asyncio
import itertools
from asyncio import TimerHandle
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

_waiting_order = itertools.count()  # one event loop per process: no lock needed
REQUEST_TIMEOUT_RESPONSE = (
    b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
    b"content-length: 36\r\nconnection: close\r\n\r\nthe request did not arrive in time\r\n"
)


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a per-request read deadline and a cap on open connections.

    Configure through :func:`guarded_protocol`, which sets the two class attributes.
    """

    request_timeout_s: float = 10.0
    max_connections: int = 1000

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._read_deadline: TimerHandle | None = None
        self._waiting_since = 0  # order in which connections began to wait (uvloop's clock has ties)

    # -- the deadline ------------------------------------------------------------------------

    def _arm(self) -> None:
        self._disarm()
        self._waiting_since = next(_waiting_order)
        self._read_deadline = self.loop.call_later(self.request_timeout_s, self._request_timed_out)

    def _disarm(self) -> None:
        if self._read_deadline is not None:
            self._read_deadline.cancel()
            self._read_deadline = None

    @property
    def waiting_for_request(self) -> bool:
        """True while the connection waits for (the rest of) a request."""
        return self._read_deadline is not None

    def _request_timed_out(self) -> None:
        self._read_deadline = None
        if self.transport.is_closing():
            return
        if self.cycle is None or self.cycle.response_complete:
            self.transport.write(REQUEST_TIMEOUT_RESPONSE)  # no response in progress: nothing to interleave with
        self.transport.close()  # a body still arriving: the application sees the client disconnect

    # -- uvicorn's callbacks -------------------------------------------------------------------

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()
        if len(self.connections) > self.max_connections:
            self._close_longest_waiting()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def on_message_complete(self) -> None:
        self._disarm()  # the whole request is in: from here on it is the application's time
        super().on_message_complete()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and not self.pipeline:
            self._arm()  # waiting for the next request on this kept-alive connection

    def _close_longest_waiting(self) -> None:
        waiting = [c for c in self.connections if isinstance(c, GuardedHttpProtocol) and c.waiting_for_request]
        if not waiting:
            self.transport.close()  # every other connection is busy with a request: refuse this one
            return
        oldest = min(waiting, key=lambda c: c._waiting_since)
        oldest._disarm()
        oldest.transport.close()


def guarded_protocol(*, request_timeout_s: float, max_connections: int) -> type[GuardedHttpProtocol]:
    """A :class:`GuardedHttpProtocol` class with these limits, for ``uvicorn.Config(http=...)``."""
    return type(
        "ConfiguredGuardedHttpProtocol",
        (GuardedHttpProtocol,),
        {"request_timeout_s": request_timeout_s, "max_connections": max_connections},
    )
