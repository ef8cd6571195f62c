"""A TCP proxy on 127.0.0.1 between a gateway and the centre that can break the link on purpose.

Modes (set at any time; a connection keeps the mode it was accepted in):

- ``pass``: bytes both ways, untouched;
- ``drop``: connections are dropped mid-request, alternately (a) after part of the request
  reached the centre (the centre stores nothing) and (b) after the whole request reached the
  centre and its answer came back, which the gateway never gets (the centre stored the batch;
  the gateway must send it again and the centre count it a duplicate);
- ``hold``: the request goes to the centre, the answer is held back until the proxy is closed
  (a gateway killed meanwhile is killed mid-upload, after the centre stored its batch).

HTTP requests are read by their Content-Length (the uplink sends no chunked bodies).
"""
from __future__ import annotations

import contextlib
import socket
import threading
from typing import Literal

Mode = Literal["pass", "drop", "hold"]
IO_TIMEOUT_S = 30.0


class LinkProxy:
    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.mode: Mode = "pass"
        self.dropped = 0  # connections dropped in drop mode
        self.held = 0  # answers held back in hold mode
        self._cond = threading.Condition()
        self._closing = threading.Event()
        self._sockets: list[socket.socket] = []
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def set_mode(self, mode: Mode) -> None:
        """From now on new connections get ``mode``; open ones are cut (a kept-alive connection would
        carry on in its old mode)."""
        with self._cond:
            self.mode = mode
            sockets, self._sockets = self._sockets, []
        for sock in sockets:
            _close(sock)

    def wait_for(self, what: Literal["dropped", "held"], at_least: int, timeout_s: float) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: getattr(self, what) >= at_least, timeout_s):
                raise AssertionError(f"the proxy saw {getattr(self, what)} {what} connections, not {at_least}, "
                                     f"in {timeout_s} s")

    def close(self) -> None:
        self._closing.set()
        self.listener.close()
        with self._cond:
            for sock in self._sockets:
                _close(sock)

    # ------------------------------------------------------------------ connections
    def _accept(self) -> None:
        while not self._closing.is_set():
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            with self._cond:
                mode = self.mode
                self._sockets.append(client)
            threading.Thread(target=self._serve, args=(client, mode), daemon=True).start()

    def _upstream(self) -> socket.socket:
        sock = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=IO_TIMEOUT_S)
        with self._cond:
            self._sockets.append(sock)
        return sock

    def _serve(self, client: socket.socket, mode: Mode) -> None:
        client.settimeout(IO_TIMEOUT_S)
        try:
            upstream = self._upstream()
        except OSError:
            _close(client)  # the centre is down: the gateway sees the connection end
            return
        try:
            if mode == "pass":
                _pump_both(client, upstream)
                return
            request = _read_http_message(client)
            if mode == "drop":
                with self._cond:
                    self.dropped += 1
                    whole = self.dropped % 2 == 0
                if not whole:
                    upstream.sendall(request[: max(1, len(request) // 2)])
                    return
                upstream.sendall(request)
                _read_http_message(upstream)  # the centre answered: the gateway never hears it
                return
            upstream.sendall(request)  # hold
            answer = _read_http_message(upstream)
            with self._cond:
                self.held += 1
                self._cond.notify_all()
            self._closing.wait(IO_TIMEOUT_S)
            del answer
        except OSError:
            pass  # either side went away: the link is broken, which is what this proxy is for
        finally:
            with self._cond:
                self._cond.notify_all()
            _close(client)
            _close(upstream)


def _read_http_message(sock: socket.socket) -> bytes:
    """One HTTP request or response (headers and a Content-Length body); OSError if the peer leaves."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError("the peer closed before the headers ended")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = 0
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            length = int(value.strip())
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError("the peer closed before the body ended")
        body += chunk
    return head + b"\r\n\r\n" + body


def _pump_both(a: socket.socket, b: socket.socket) -> None:
    other = threading.Thread(target=_pump, args=(b, a), daemon=True)
    other.start()
    _pump(a, b)
    other.join(IO_TIMEOUT_S)


def _pump(source: socket.socket, sink: socket.socket) -> None:
    try:
        while chunk := source.recv(65536):
            sink.sendall(chunk)
    except OSError:
        pass  # a closed side ends the pump
    finally:
        with contextlib.suppress(OSError):  # already gone
            sink.shutdown(socket.SHUT_WR)


def _close(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):  # already closed
        sock.close()
