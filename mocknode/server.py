"""Serve mock nodes on real pseudo-terminals or TCP 127.0.0.1, with line pacing and faults.

Each node runs in its own thread: bytes in -> FrameDecoder -> MockNode.handle -> fault filter
-> paced write. A pseudo-terminal behaves like the node's USB-UART: the gateway opens the
printed /dev/pts/N (or the stable ``link_dir/<node_id>`` symlink). A disconnect closes the
pty (the gateway sees PortVanished) and, ``reconnect_after_s`` later, opens a NEW one; the
node reboots then, as a USB-powered board does. A power cycle (``reboot_every_s``, or
:meth:`MockNodeServer.power_cycle`, SIGUSR1 to ``pipesentry mock-node``) reboots the node
with its port left open, as a brown-out of a board whose USB-UART has its own supply does.

Everything that happens in the node's time runs on its injectable ``clock`` (seconds,
monotonic): the scenario (defects appearing, temperature drifting), the fault schedule
(disconnects, reconnects, stalls) and the time an averaged ACQUIRE takes. A test passes a
clock it advances itself instead of sleeping. Only the line's byte rate (``pace``) is real
time: it is what the gateway's serial timeouts see. A firmware that is BUSY while it acquires
(``firmware.busy_while_acquiring``) keeps reading requests during the acquisition and sends
its reply when the acquisition's time has passed on that clock.
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

from mocknode.faults import Violation
from mocknode.node import MockNode
from mocknode.scenario import NodeScenario
from mocknode.violations import wire_bytes
from protocol.cobs import CobsError, cobs_decode
from protocol.framing import HEADER, HEADER_BYTES, Frame, FrameCrcError, FrameDecoder, FrameError
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
        self._power_cycle = threading.Event()
        self._deferred: tuple[float, list[Frame]] | None = None  # replies of an acquisition still running
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

    def power_cycle(self) -> None:
        """Reboot the node between requests, its port staying open (thread-safe)."""
        self._power_cycle.set()

    # ------------------------------------------------------------------ main loop
    def run(self) -> None:
        try:
            self._power_up_garbage()
            next_disconnect = self._next_at(self.faults.disconnect_every_s)
            next_reboot = self._next_at(self.faults.reboot_every_s)
            decoder = self._decoder()
            while not self.stop_event.is_set():
                if next_disconnect is not None and self.clock() >= next_disconnect:
                    self._disconnect()
                    decoder = self._decoder()
                    next_disconnect = self._next_at(self.faults.disconnect_every_s)
                    continue
                if self._power_cycle.is_set() or (next_reboot is not None and self.clock() >= next_reboot):
                    self._power_cycle.clear()
                    self._reboot()
                    decoder = self._decoder()  # the receive buffer is RAM too
                    next_reboot = self._next_at(self.faults.reboot_every_s)
                port = self._port
                if port is None:  # closed under us (stop or disconnect fault)
                    break
                ready, _, _ = select.select([port], [], [], self._send_due_replies())
                if not ready:
                    continue
                for item in decoder.feed(port.read()):
                    if isinstance(item, FrameError):
                        self.node.note_frame_error(isinstance(item, FrameCrcError))
                        self._answer_corrupt(item)
                        continue
                    if self._stalls():
                        continue
                    self._send_due_replies()
                    self._answer(item)
        finally:
            self._close_port()

    def _decoder(self) -> FrameDecoder:
        if Violation.ACCEPTS_OVERSIZED in self.node.violations:
            return FrameDecoder(max_encoded_bytes=1 << 20, max_frame_bytes=1 << 20)
        return FrameDecoder()

    def _next_at(self, every_s: float) -> float | None:
        return self.clock() + every_s if every_s > 0 else None

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

    def _answer(self, request: Frame) -> None:
        replies = self.node.handle(request)
        service_s = self.node.last_service_s
        if service_s > 0 and self.node.scenario.firmware.busy_while_acquiring:
            self._flush_deferred()
            self._deferred = (self.clock() + service_s, replies)  # other requests get BUSY meanwhile
            return
        if self.pace and service_s > 0:
            self._wait_node_s(service_s)  # ACQUIRE averaging takes the node's time; requests wait behind it
        self._send_replies(replies)

    def _send_replies(self, replies: list[Frame]) -> None:
        for frame in replies:
            if frame.msg_type == MsgType.BULK_CHUNK and self._rng.random() < self.faults.reboot_probability:
                self._reboot()
                return
            self._send(wire_bytes(frame))

    def _send_due_replies(self) -> float:
        """Send the deferred replies once their acquisition is done; the time to wait for input."""
        if self._deferred is None:
            return _POLL_S
        left_s = self._deferred[0] - self.clock()
        if left_s > 0:
            return min(_POLL_S, left_s)
        self._flush_deferred()
        return _POLL_S

    def _flush_deferred(self) -> None:
        deferred, self._deferred = self._deferred, None
        if deferred is not None:
            self._send_replies(deferred[1])

    def _answer_corrupt(self, error: FrameError) -> None:
        """Violation answers_corrupt_frames: reply to a frame whose CRC failed, trusting its header."""
        if not isinstance(error, FrameCrcError) or Violation.ANSWERS_CORRUPT_FRAMES not in self.node.violations:
            return
        try:
            body = cobs_decode(error.raw)
        except CobsError:
            return
        version, msg_type, flags, _, seq, request_id = HEADER.unpack_from(body)
        request = Frame(msg_type, request_id, body[HEADER_BYTES:-4], flags, seq, version)
        self._send_replies(self.node.handle(request))

    def _reboot(self) -> None:
        self.reboots += 1
        self._deferred = None  # an acquisition's reply dies with the RAM
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
        self._deferred = None
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

    def power_cycle(self) -> None:
        """Reboot every node (ports stay open); each comes back with its power-up settings."""
        for runner in self.runners.values():
            runner.power_cycle()

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
