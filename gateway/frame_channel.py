"""Frames between the gateway and one node, over a :class:`nodelink.transport.SerialTransport`.

A request goes out numbered (``seq``) in the session's protocol version (``HELLO_VERSION``
until INFO has negotiated one); of what comes back, only the replies to the request id asked
about are kept, read per :func:`gateway.reply_decoding.decode_reply`, and a refusal of the
version (ERROR BAD_VERSION) is a :class:`ProtocolMismatch`. Frames that fail their CRC or
framing are counted and dropped.
"""
from __future__ import annotations

import time
from collections.abc import Iterator

from gateway.node_errors import ProtocolMismatch
from gateway.reply_decoding import decode_reply
from nodelink.transport import SerialTransport
from protocol.framing import Frame, FrameDecoder, FrameError, encode_frame
from protocol.messages import ErrorCode, ErrorReply, Message
from protocol.versions import HELLO_VERSION


class FrameChannel:
    """The framed link to one node: ``serial.serial_for_url(url)`` (a device path, socket://, loop://)."""

    def __init__(self, url: str, baudrate: int, exclusive: bool) -> None:
        self.seq = 0  # of the last request sent
        self.version: int | None = None  # the session's, once INFO has negotiated it
        self.frame_errors = 0
        self._decoder = FrameDecoder()
        self._transport = SerialTransport(url, baudrate=baudrate, exclusive=exclusive)

    def close(self) -> None:
        self._transport.close()

    def reopen(self) -> None:
        """Open the port again after :class:`PortVanished` (e.g. a re-plugged USB-UART)."""
        self._transport.reopen()
        self._decoder = FrameDecoder()

    def send(self, message: Message, request_id: int) -> None:
        self.seq = (self.seq + 1) & 0xFFFF
        version = HELLO_VERSION if self.version is None else self.version  # INFO goes out in version 1
        frame = Frame(message.TYPE, request_id, message.encode(version), seq=self.seq, version=version)
        self._transport.write(encode_frame(frame))

    def replies(self, request_id: int, timeout_s: float) -> Iterator[tuple[Frame, Message]]:
        """Yield (frame, message) replies to ``request_id`` until ``timeout_s`` passes without one."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            for item in self._decoder.feed(self._transport.read(min(left, 0.1))):
                if isinstance(item, FrameError):
                    self.frame_errors += 1
                    continue
                if not item.is_reply:
                    continue  # our own request echoed (loop://) or another host's
                if item.request_id != request_id:
                    continue  # a late reply to an earlier attempt
                message = decode_reply(item, self.version)
                if isinstance(message, ErrorReply) and message.code == ErrorCode.BAD_VERSION:
                    raise ProtocolMismatch(f"node refused protocol version {self.version or HELLO_VERSION}: "
                                           f"{message.detail}")
                yield item, message
                deadline = time.monotonic() + timeout_s
