"""Slow and silent clients (slowloris) cannot deny the API to others.

Real sockets against a real server on 127.0.0.1: `pipesentry api` as an operator starts it for
the many-connections case (its own process, so its connections and the attacker's do not share
one open-file limit), and the in-process test server, with a short request deadline, for the
deadline and the connection cap. Every wait is bounded; nothing asserts a duration.
"""
from __future__ import annotations

import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.settings import ApiSettings
from tests.support.api_fixtures import (
    Api,
    ApiServer,
    copy_database,
    create_test_keys,
    fleet_database,
    free_port,
)
from tests.support.process_harness import Proc, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(180)]

HALF_OPEN = 520  # the count: more than uvicorn's limit_concurrency=512 the API used to run with
PARTIAL_HEAD = b"GET /api/v1/nodes HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "  # never finished
SHORT_DEADLINE_S = 1.0
SMALL_CAP = 40


def half_open(port: int, count: int) -> list[socket.socket]:
    """``count`` connections that each send part of a request head and then nothing."""
    sockets = []
    for _ in range(count):
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(PARTIAL_HEAD)
        sockets.append(sock)
    return sockets


def closed_by_server(sock: socket.socket, timeout_s: float) -> bytes | None:
    """What the server sent before closing ``sock`` (None if it is still open after ``timeout_s``)."""
    sock.settimeout(timeout_s)
    received = b""
    try:
        while chunk := sock.recv(4096):
            received += chunk
    except TimeoutError:
        return None
    except ConnectionResetError:
        pass
    return received


def open_sockets(pid: int) -> int:
    return sum(1 for fd in Path(f"/proc/{pid}/fd").iterdir() if fd.resolve(strict=False).name.startswith("socket:"))


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    path = copy_database(fleet_database(tmp_path_factory.getbasetemp()), tmp_path_factory.mktemp("slow") / "api.db")
    url = f"sqlite:///{path}"
    return url, create_test_keys(url).viewer


def port_of(api: Api) -> int:
    return int(api.base_url.rsplit(":", 1)[1])


@pytest.fixture(scope="module")
def capped(database: tuple[str, str]) -> Iterator[Api]:
    """The test server with room for 40 connections (and the default, far longer, request deadline)."""
    url, _ = database
    with ApiServer(ApiSettings(database_url=url, max_connections=SMALL_CAP)) as server:
        yield Api(server.base_url, url, create_test_keys(url))


@pytest.fixture(scope="module")
def guarded(database: tuple[str, str]) -> Iterator[Api]:
    """The test server with a 1 s request deadline."""
    url, _ = database
    settings = ApiSettings(database_url=url, request_timeout_s=SHORT_DEADLINE_S)
    with ApiServer(settings) as server:
        yield Api(server.base_url, url, create_test_keys(url))


def test_520_half_open_connections_do_not_make_the_api_refuse_others(database, tmp_path):
    url, viewer = database
    port = free_port()
    api = Proc([sys.executable, "-c", "import typer; from pipesentry.commands.api import api; typer.run(api)",
                "--database-url", url, "--port", str(port), "--log-level", "warning"], tmp_path, "api")
    sockets: list[socket.socket] = []
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until(lambda: httpx.get(f"{base}/readyz", timeout=2).status_code == 200, 30, 0.1, what="api ready")
        sockets = half_open(port, HALF_OPEN)
        wait_until(lambda: open_sockets(api.popen.pid) >= HALF_OPEN, 30, 0.1,
                   what=f"the server to hold {HALF_OPEN} connections")
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {viewer}"}, timeout=10) as client:
            answers = [client.get(path).status_code for path in ("/api/v1/nodes", "/healthz", "/readyz")]
        print(f"slowloris: {HALF_OPEN} half-open connections held, others answered {answers}")
        assert answers == [200, 200, 200], api.stderr[-2000:]
    finally:
        for sock in sockets:
            sock.close()
        api.terminate()
        api.close()


def test_a_request_head_that_never_completes_is_answered_408_and_closed(guarded: Api):
    [sock] = half_open(port_of(guarded), 1)
    with sock:
        received = closed_by_server(sock, timeout_s=20 * SHORT_DEADLINE_S)
    assert received is not None, "the server kept a half-open connection"
    assert received.startswith(b"HTTP/1.1 408 ")


def test_a_head_trickled_a_byte_at_a_time_is_still_cut_off(guarded: Api):
    """uvicorn's keep-alive timer restarts with every byte; the request deadline does not."""
    with socket.create_connection(("127.0.0.1", port_of(guarded)), timeout=10) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nX-Slow: ")
        sock.settimeout(0.2)
        cut_off = False
        for _ in range(200):  # a byte every 0.2 s for at most 40 s: 40 deadlines
            try:
                sock.sendall(b"a")
                sock.recv(4096)  # the 408, or b"" once closed
            except TimeoutError:
                continue  # nothing from the server yet
            except (BrokenPipeError, ConnectionResetError):
                pass
            cut_off = True
            break
    assert cut_off, "a client trickling its request head kept the connection"


def test_a_body_that_stops_arriving_is_cut_off(guarded: Api):
    with socket.create_connection(("127.0.0.1", port_of(guarded)), timeout=10) as sock:
        sock.sendall(b"POST /api/v1/keys HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                     b"Authorization: Bearer " + guarded.keys.admin.encode() + b"\r\n"
                     b"Content-Length: 1000\r\n\r\n{\"name\": ")
        received = closed_by_server(sock, timeout_s=20 * SHORT_DEADLINE_S)
    assert received is not None, "the server waited for ever for the rest of a body"
    assert b"201" not in received.split(b"\r\n", 1)[0]


def test_beyond_the_connection_cap_the_longest_waiting_connections_are_closed(capped: Api):
    sockets = half_open(port_of(capped), SMALL_CAP + 20)
    try:
        with capped.client(capped.keys.viewer) as client:
            answer = client.get("/api/v1/nodes").status_code
        # Closed without a word (not a 408: this server's deadline is far off) = evicted.
        evicted = [i for i, sock in enumerate(sockets) if closed_by_server(sock, timeout_s=0.1) == b""]
        print(f"slowloris: {len(sockets)} half-open connections against a cap of {SMALL_CAP}: a request answered "
              f"{answer}, {len(evicted)} connections closed, the oldest first")
        assert answer == 200
        assert len(evicted) >= 20 and evicted == list(range(len(evicted)))
    finally:
        for sock in sockets:
            sock.close()
