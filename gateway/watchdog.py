"""systemd notification: READY once started, watchdog pings only while every worker makes progress.

A worker *makes progress* when its poll loop comes round, whether the node answered or not:
an unplugged node is not a hung gateway, but a loop stuck anywhere is, and then the pings
stop so that systemd (``WatchdogSec``) restarts the daemon.
"""
from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Mapping


def _notify_socket_address() -> str | None:
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return None
    return "\0" + address[1:] if address.startswith("@") else address


def sd_notify(message: str) -> bool:
    """Send one sd_notify datagram; False when not run under systemd (or the socket is gone)."""
    address = _notify_socket_address()
    if address is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(message.encode())
        return True
    except OSError:
        return False


def watchdog_interval_s(default_s: float = 10.0) -> float:
    """Half of systemd's WatchdogSec (WATCHDOG_USEC), the recommended ping period."""
    usec = os.environ.get("WATCHDOG_USEC")
    try:
        return max(0.05, int(usec) / 2e6) if usec else default_s
    except ValueError:
        return default_s


class Heartbeats:
    """Last-progress times of the worker loops, written by the workers, read by the watchdog."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._beats: dict[str, float] = {}

    def beat(self, name: str) -> None:
        with self._lock:
            self._beats[name] = self._clock()

    def snapshot(self) -> Mapping[str, float]:
        with self._lock:
            return dict(self._beats)

    def stalled(self, limits_s: Mapping[str, float]) -> list[str]:
        """Workers whose last beat is older than their limit (a worker that never beat counts from start)."""
        now = self._clock()
        beats = self.snapshot()
        return sorted(name for name, limit in limits_s.items() if now - beats.get(name, now) > limit)
