"""Byte transport to one node: a pyserial port opened from a URL (device path, socket://, loop://).

Knows ports only: bytes in, bytes out, and the difference between "nothing arrived" and
"the port is gone". Every fault of the port itself becomes :class:`PortVanished`.
"""
from __future__ import annotations

import contextlib
import time

import serial

_POLL_S = 0.02


def _termios_error() -> type[Exception]:
    """POSIX: pyserial's flush()/reset_input_buffer() call termios, whose error is not an OSError."""
    try:
        from termios import error
    except ImportError:  # pragma: no cover - Windows
        return OSError
    return error


# What a port that vanished (unplugged USB-UART, closed pty, dropped socket) raises.
PORT_ERRORS: tuple[type[Exception], ...] = (serial.SerialException, OSError, _termios_error())
_OPEN_ERRORS: tuple[type[Exception], ...] = (*PORT_ERRORS, ValueError)  # ValueError: a malformed port URL

class NodeLinkError(Exception):
    """Base of every error of talking to a node: the port, the protocol, the node's answers."""


class PortVanished(NodeLinkError):
    """The serial device or socket disappeared (unplugged, closed); ``reopen()`` is the caller's call."""


class SerialTransport:
    """One open pyserial port; ``read`` waits at most ``timeout_s`` for the first byte."""

    def __init__(self, url: str, baudrate: int = 230400, exclusive: bool = True) -> None:
        self.url = url
        self.baudrate = baudrate
        # Locking (TIOCEXCL + flock) only exists for real device paths, not for URL handlers.
        self.exclusive = exclusive and "://" not in url
        self._port: serial.SerialBase | None = None
        self.open()

    def open(self) -> None:
        # A fixed short poll: changing a posix port's timeout re-runs tcsetattr on every call.
        kwargs = {"baudrate": self.baudrate, "timeout": _POLL_S, "write_timeout": 5.0}
        if self.exclusive:
            kwargs["exclusive"] = True
        try:
            self._port = serial.serial_for_url(self.url, **kwargs)
        except _OPEN_ERRORS as exc:
            self._port = None
            raise PortVanished(f"cannot open {self.url}: {exc}") from exc

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(*PORT_ERRORS):  # a port that already vanished has nothing left to release
                port.close()

    def reopen(self) -> None:
        """Close (if still open) and open the same URL again; raises PortVanished if absent."""
        self.close()
        self.open()

    @property
    def is_open(self) -> bool:
        return self._port is not None

    def _require(self) -> serial.SerialBase:
        if self._port is None:
            raise PortVanished(f"{self.url} is not open")
        return self._port

    def write(self, data: bytes) -> None:
        port = self._require()
        try:
            port.write(data)
            port.flush()
        except PORT_ERRORS as exc:
            self.close()
            raise PortVanished(f"write to {self.url} failed: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        """Bytes that arrive within ``timeout_s`` (b"" if none): at least one, then all waiting."""
        port = self._require()
        deadline = time.monotonic() + max(0.0, timeout_s)
        try:
            while True:
                first = port.read(1)
                if first:
                    return first + self._read_available(port)
                if time.monotonic() >= deadline:
                    return b""
        except PORT_ERRORS as exc:
            self.close()
            raise PortVanished(f"read from {self.url} failed: {exc}") from exc

    @staticmethod
    def _read_available(port: serial.SerialBase) -> bytes:
        if isinstance(port, serial.Serial):  # a real device path: the driver knows the count
            waiting = port.in_waiting
            return port.read(waiting) if waiting else b""
        # URL handlers (socket://) report in_waiting as 0/1: read non-blocking instead.
        port.timeout = 0
        try:
            return port.read(65536)
        finally:
            port.timeout = _POLL_S

    def discard_input(self) -> None:
        port = self._require()
        try:
            port.reset_input_buffer()
        except PORT_ERRORS as exc:
            self.close()
            raise PortVanished(f"{self.url}: {exc}") from exc
