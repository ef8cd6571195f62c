"""Serve mock nodes on real pseudo-terminals or TCP 127.0.0.1, with line pacing and faults.

Each node runs in its own thread: bytes in -> FrameDecoder -> MockNode.handle -> fault filter
-> paced write. A pseudo-terminal behaves like the node's USB-UART: the gateway opens the
printed /dev/pts/N (or the stable ``link_dir/<node_id>`` symlink). A disconnect closes the
pty (the gateway sees PortVanished) and, ``reconnect_after_s`` later, opens a NEW one; the
node reboots then, as a USB-powered board does.

Everything that happens in the node's time runs on its injectable ``clock`` (seconds,
monotonic): the scenario (defects appearing, temperature drifting), the fault schedule
(disconnects, reconnects, stalls) and the time an averaged ACQUIRE takes. A test passes a
clock it advances itself instead of sleeping. Only the line's byte rate (``pace``) is real
time: it is what the gateway's serial timeouts see.
"""
from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np

from mocknode.node import MockNode
from mocknode.scenario import NodeScenario
from protocol.framing import FrameCrcError, FrameDecoder, FrameError, encode_frame
from protocol.messages import MsgType

_POLL_S = 0.05
_WRITE_SLICE_BYTES = 256


class ServerError(RuntimeError):
    """The mock node server could not open its ports."""


class _PtyPort:
    """A pseudo-terminal pair; the slave path is what the gateway opens."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: a plain byte pipe like a UART
        os.set_blocking(self.master, False)
        self.url = os.ttyname(self._slave)

    def fileno(self) -> int:
        return self.master

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise

    def send(self, data: bytes, stop: threading.Event) -> bool:
        view = memoryview(data)
        while view and not stop.is_set():
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                select.select([], [self.master], [], _POLL_S)  # the gateway is not reading: wait
        return not view

    def close(self) -> None:
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class _TcpPort:
    """A listening socket on 127.0.0.1 with at most one connected gateway."""

    def __init__(self, port: int) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind(("127.0.0.1", port))
        except OSError as exc:
            self._listener.close()
            raise ServerError(f"cannot listen on 127.0.0.1:{port}: {exc}") from exc
        self._listener.listen(1)
        self._listener.setblocking(False)
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._conn: socket.socket | None = None

    def fileno(self) -> int:
        return self._conn.fileno() if self._conn is not None else self._listener.fileno()

    def read(self) -> bytes:
        if self._conn is None:
            try:
                self._conn, _ = self._listener.accept()
                self._conn.setblocking(False)
            except BlockingIOError:
                pass
            return b""
        try:
            data = self._conn.recv(65536)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:  # the gateway hung up; wait for the next one
            self._conn.close()
            self._conn = None
        return data

    def send(self, data: bytes, stop: threading.Event) -> bool:
        if self._conn is None:
            return False
        view = memoryview(data)
        while view and not stop.is_set():
            try:
                view = view[self._conn.send(view):]
            except BlockingIOError:
                select.select([], [self._conn], [], _POLL_S)
            except OSError:
                self._conn.close()
                self._conn = None
                return False
        return not view

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        self._listener.close()


class NodeRunner(threading.Thread):
    """Serves one MockNode on one port until ``stop``; applies the scenario's FaultSpec."""

    def __init__(
        self, scenario: NodeScenario, kind: Literal["pty", "tcp"] = "pty", port: int = 0, baud: int = 230400,
        pace: bool = False, link_dir: Path | None = None, on_port: Callable[[str, str], None] | None = None,
        stop: threading.Event | None = None, clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(name=f"mocknode-{scenario.node_id}", daemon=True)
        self.clock = clock
        self.node = MockNode(scenario, clock)
        self.faults = scenario.faults
        self.kind = kind
        self.tcp_port = port
        self.bytes_per_s = baud / 10.0  # 8N1: ten bit times per byte
        self.pace = pace
        self.link_dir = link_dir
        self.on_port = on_port
        self.stop_event = stop or threading.Event()
        self._rng = np.random.default_rng(scenario.seed + 7919)
        self._changed = threading.Condition()
        self.generation = 0  # +1 every time a (new) port opens
        self.url = ""  # set by _open_port below, before anyone can read it
        self.reboots = 0
        self._port: _PtyPort | _TcpPort | None = None
        self._line_free_at = 0.0
        self._open_port()

    # ------------------------------------------------------------------ ports
    def _open_port(self) -> None:
        port = _PtyPort() if self.kind == "pty" else _TcpPort(self.tcp_port)
        if isinstance(port, _TcpPort):
            self.tcp_port = port.port  # keep the same port across reconnects
        self._port = port
        if self.link_dir is not None and self.kind == "pty":
            link = self.link_path
            tmp = link.with_name(f".{link.name}.tmp")
            tmp.unlink(missing_ok=True)
            os.symlink(port.url, tmp)
            os.replace(tmp, link)
        with self._changed:
            self.url = port.url
            self.generation += 1
            self._changed.notify_all()
        if self.on_port is not None:
            self.on_port(self.node.scenario.node_id, port.url)

    @property
    def link_path(self) -> Path:
        assert self.link_dir is not None
        return self.link_dir / self.node.scenario.node_id

    def wait_for_generation(self, generation: int, timeout_s: float) -> bool:
        """Block until a port of at least ``generation`` is open (True) or the timeout (False)."""
        with self._changed:
            return self._changed.wait_for(lambda: self.generation >= generation, timeout_s)

    # ------------------------------------------------------------------ main loop
    def run(self) -> None:
        try:
            self._power_up_garbage()
            next_disconnect = self._next_disconnect_at()
            decoder = FrameDecoder()
            while not self.stop_event.is_set():
                if next_disconnect is not None and self.clock() >= next_disconnect:
                    self._disconnect()
                    decoder = FrameDecoder()
                    next_disconnect = self._next_disconnect_at()
                    continue
                port = self._port
                if port is None:  # closed under us (stop or disconnect fault)
                    break
                ready, _, _ = select.select([port], [], [], _POLL_S)
                if not ready:
                    continue
                for item in decoder.feed(port.read()):
                    if isinstance(item, FrameError):
                        self.node.note_frame_error(isinstance(item, FrameCrcError))
                        continue
                    if self._stalls():
                        continue
                    self._answer(item)
        finally:
            self._close_port()

    def _next_disconnect_at(self) -> float | None:
        every = self.faults.disconnect_every_s
        return self.clock() + every if every > 0 else None

    def _wait_node_s(self, seconds: float) -> bool:
        """Let ``seconds`` of the node's clock pass (True if the server is stopped meanwhile)."""
        deadline = self.clock() + seconds
        while (left := deadline - self.clock()) > 0:
            if self.stop_event.wait(min(left, _POLL_S)):
                return True
        return self.stop_event.is_set()

    def _stalls(self) -> bool:
        if self.faults.stall_probability > 0 and self._rng.random() < self.faults.stall_probability:
            self._wait_node_s(self.faults.stall_s)  # the node hangs; requests pile up unread
            return True
        return False

    def _answer(self, request) -> None:
        replies = self.node.handle(request)
        if self.pace and self.node.last_service_s > 0:
            self._wait_node_s(self.node.last_service_s)  # ACQUIRE averaging takes the node's time
        for frame in replies:
            if frame.msg_type == MsgType.BULK_CHUNK and self._rng.random() < self.faults.reboot_probability:
                self._reboot()
                return
            self._send(encode_frame(frame))

    def _reboot(self) -> None:
        self.reboots += 1
        self.node.boot()
        self._power_up_garbage()

    def _power_up_garbage(self) -> None:
        n = self.faults.garbage_on_power_up
        if n:
            self._send(self._rng.integers(0, 256, n, dtype=np.uint8).tobytes(), faults=False)

    def _disconnect(self) -> None:
        self._close_port()
        if self._wait_node_s(self.faults.reconnect_after_s):
            return
        self.node.boot()  # USB-powered: unplugging is a power cycle
        self.reboots += 1
        self._open_port()
        self._power_up_garbage()

    def _close_port(self) -> None:
        if self._port is not None:
            self._port.close()
            self._port = None
        if self.link_dir is not None and self.kind == "pty":
            self.link_path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ line
    def _inject(self, data: bytes) -> bytes:
        faults = self.faults
        if not (faults.corrupt_byte_rate or faults.drop_byte_rate):
            return data
        raw = np.frombuffer(data, dtype=np.uint8).copy()
        corrupt = self._rng.random(raw.size) < faults.corrupt_byte_rate
        raw[corrupt] ^= (1 << self._rng.integers(0, 8, int(corrupt.sum()))).astype(np.uint8)
        keep = self._rng.random(raw.size) >= faults.drop_byte_rate
        return raw[keep].tobytes()

    def _send(self, data: bytes, faults: bool = True) -> None:
        data = self._inject(data) if faults else data
        port = self._port
        if port is None:  # the port was closed (a disconnect fault): the reply is lost, as on a real line
            return
        if not self.pace:
            port.send(data, self.stop_event)
            return
        for i in range(0, len(data), _WRITE_SLICE_BYTES):
            piece = data[i : i + _WRITE_SLICE_BYTES]
            now = time.monotonic()  # real time: the byte rate the gateway's timeouts see
            self._line_free_at = max(self._line_free_at, now)
            if self.stop_event.wait(max(0.0, self._line_free_at - now)):
                return
            if not port.send(piece, self.stop_event):
                return
            self._line_free_at += len(piece) / self.bytes_per_s


class MockNodeServer:
    """Several nodes in one process; ``urls`` maps node id to the current port URL."""

    def __init__(
        self, scenarios: list[NodeScenario], kind: Literal["pty", "tcp"] = "pty", base_port: int = 0,
        baud: int = 230400, pace: bool = False, link_dir: Path | None = None,
        on_port: Callable[[str, str], None] | None = None, clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``clock``: the nodes' time (seconds, monotonic), shared by all of them; see the module's docstring."""
        if link_dir is not None:
            link_dir.mkdir(parents=True, exist_ok=True)
        self.stop_event = threading.Event()
        self.runners: dict[str, NodeRunner] = {}
        try:
            for i, scenario in enumerate(scenarios):
                port = base_port + i if base_port else 0
                self.runners[scenario.node_id] = NodeRunner(
                    scenario, kind, port, baud, pace, link_dir, on_port, self.stop_event, clock)
        except Exception:
            self.stop_event.set()
            for runner in self.runners.values():
                runner._close_port()
            raise

    @property
    def urls(self) -> dict[str, str]:
        return {node_id: runner.url for node_id, runner in self.runners.items()}

    def start(self) -> MockNodeServer:
        for runner in self.runners.values():
            runner.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop every node thread and close its port; returns once they have ended."""
        self.stop_event.set()
        for runner in self.runners.values():
            if runner.is_alive():
                runner.join(timeout_s)
            else:
                runner._close_port()

    def __enter__(self) -> MockNodeServer:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
