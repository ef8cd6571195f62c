"""One checker's conversation with a node: requests out (well-formed or deliberately not),
every reply frame collected with the bytes it came as, BUSY retried like the gateway does."""
from __future__ import annotations

import random
import struct
import time
from dataclasses import dataclass, field

from nodelink.transport import NodeLinkError, SerialTransport
from protocol.cobs import CobsError, cobs_decode, cobs_encode
from protocol.crc import crc32c
from protocol.framing import FLAG_LAST, HEADER, Frame, FrameDecoder, FrameError, encode_frame
from protocol.messages import ErrorCode, ErrorReply, Message, MessageError, MsgType, decode_message
from protocol.versions import HELLO_VERSION


class CheckAborted(NodeLinkError):
    """The node stopped answering in a way no requirement can be checked past (exit 2)."""


def hex_bytes(data: bytes, limit: int = 48) -> str:
    """``data`` as spaced hex, cut after ``limit`` bytes with the full length named."""
    shown = " ".join(f"{b:02x}" for b in data[:limit])
    return shown if len(data) <= limit else f"{shown} ... ({len(data)} bytes)"


def frame_body(frame: Frame) -> bytes:
    """Header, payload and CRC of a decoded frame: what the node sent before COBS."""
    body = HEADER.pack(frame.version, frame.msg_type, frame.flags, 0, frame.seq, frame.request_id) + frame.payload
    return body + struct.pack("<I", crc32c(body))


def error_body(error: FrameError) -> bytes:
    """The decoded bytes of a rejected frame where COBS allows, else the bytes as they came."""
    try:
        return cobs_decode(error.raw)
    except CobsError:
        return error.raw


@dataclass
class Reply:
    """The frames one request brought back (in order) and what they decode to."""

    frames: list[Frame] = field(default_factory=list)
    messages: list[Message | None] = field(default_factory=list)  # None: the payload did not parse
    bad_frames: list[FrameError] = field(default_factory=list)  # CRC/COBS/length failures meanwhile
    parse_errors: list[str] = field(default_factory=list)

    @property
    def first(self) -> Message | None:
        return self.messages[0] if self.messages else None

    @property
    def complete(self) -> bool:
        return bool(self.frames) and bool(self.frames[-1].flags & FLAG_LAST)

    def error_code(self) -> int | None:
        first = self.first
        return first.code if isinstance(first, ErrorReply) else None

    def evidence(self) -> str:
        """The bytes to show for this reply: the first bad frame, else the first frame."""
        if self.bad_frames:
            return hex_bytes(error_body(self.bad_frames[0]))
        if self.frames:
            return hex_bytes(frame_body(self.frames[0]))
        return "(no reply)"


@dataclass
class Timing:
    """The host timeouts docs/protocol.md tells an integrator to set (section 3)."""

    timeout_s: float = 1.0
    retries: int = 3
    backoff_s: float = 0.05
    shot_period_s: float = 0.01
    compute_timeout_s: float = 60.0

    def acquire_s(self, averaging: int) -> float:
        return self.timeout_s + averaging * self.shot_period_s


class Session:
    """A link to one node with the checker's bookkeeping (request ids, BUSY seen, boot ids seen)."""

    def __init__(self, url: str, timing: Timing, baudrate: int = 230400, seed: int | None = None) -> None:
        self.url = url
        self.timing = timing
        self._rng = random.Random(seed)
        self._request_id = self._rng.randrange(1, 2**31)
        self._seq = 0
        self.version = HELLO_VERSION
        self.busy_log: list[tuple[int, float, bool]] = []  # (msg_type, seconds BUSY, served in the end)
        self.boot_ids: dict[str, set[int]] = {}  # where each boot id was seen
        self._decoder = FrameDecoder()
        self._transport = SerialTransport(url, baudrate=baudrate, exclusive=True)

    def close(self) -> None:
        self._transport.close()

    # ------------------------------------------------------------------ bytes out
    def next_id(self) -> int:
        self._request_id = self._request_id % (2**32 - 1) + 1
        return self._request_id

    def frame(self, message: Message | None = None, *, msg_type: int | None = None, payload: bytes | None = None,
              version: int | None = None, request_id: int | None = None) -> Frame:
        """A request frame: ``message`` encoded in ``version`` (default: the session's), or raw fields."""
        version = self.version if version is None else version
        self._seq = (self._seq + 1) & 0xFFFF
        if payload is None:
            assert message is not None
            payload = message.encode(min(version, 2))
        kind = msg_type if msg_type is not None else (message.TYPE if message is not None else 0)
        return Frame(kind, self.next_id() if request_id is None else request_id, payload, seq=self._seq,
                     version=version)

    def send(self, frame: Frame) -> None:
        self._transport.write(encode_frame(frame))

    def send_raw(self, data: bytes) -> None:
        self._transport.write(data)

    @staticmethod
    def wire_with_crc(frame: Frame, crc_xor: int) -> bytes:
        """``frame`` on the wire with its CRC-32C XORed by ``crc_xor`` (a corrupt frame)."""
        body = HEADER.pack(frame.version, frame.msg_type, frame.flags, 0, frame.seq, frame.request_id) + frame.payload
        return b"\x00" + cobs_encode(body + struct.pack("<I", crc32c(body) ^ crc_xor)) + b"\x00"

    # ------------------------------------------------------------------ bytes in
    def collect(self, request_ids: set[int], timeout_s: float, *, until_last: bool = True) -> dict[int, Reply]:
        """Replies to ``request_ids``: each ends at its LAST frame; all end when no frame has come for
        ``timeout_s`` (or, with ``until_last``, once every id has its LAST frame)."""
        replies = {rid: Reply() for rid in request_ids}
        deadline = time.monotonic() + timeout_s
        while True:
            if until_last and all(r.complete for r in replies.values()):
                return replies
            left = deadline - time.monotonic()
            if left <= 0:
                return replies
            for item in self._decoder.feed(self._transport.read(min(left, 0.05))):
                if isinstance(item, FrameError):
                    for reply in replies.values():
                        reply.bad_frames.append(item)
                    continue
                deadline = time.monotonic() + timeout_s
                found = replies.get(item.request_id)
                if found is None or not item.is_reply or found.complete:
                    continue  # a late answer to an earlier probe
                reply = found
                reply.frames.append(item)
                try:
                    message = decode_message(item.msg_type, item.payload,
                                             item.version if item.msg_type in (MsgType.ERROR, MsgType.INFO_REPLY)
                                             else self.version)
                except MessageError as exc:
                    reply.messages.append(None)
                    reply.parse_errors.append(str(exc))
                    continue
                reply.messages.append(message)
                boot_id = getattr(message, "boot_id", None)
                if boot_id is not None:
                    self.boot_ids.setdefault(type(message).__name__, set()).add(boot_id)

    def exchange(self, frame: Frame, timeout_s: float | None = None) -> Reply:
        """Send one frame and collect its reply (no retry)."""
        self.send(frame)
        return self.collect({frame.request_id}, self.timing.timeout_s if timeout_s is None else timeout_s)[
            frame.request_id]

    def command(self, message: Message, timeout_s: float | None = None, **frame_args) -> Reply:
        """Send ``message``; resend the same frame after a timeout or BUSY, with backoff, as the
        gateway does (docs/protocol.md section 3); BUSY episodes are logged for R-BUSY-1."""
        frame = self.frame(message, **frame_args)
        busy_since: float | None = None
        reply = Reply()
        for attempt in range(self.timing.retries + 1):
            if attempt:
                time.sleep(self._rng.uniform(0.5, 1.0) * min(2.0, self.timing.backoff_s * 2 ** (attempt - 1)))
            reply = self.exchange(frame, timeout_s)
            if reply.error_code() == ErrorCode.BUSY:
                busy_since = busy_since or time.monotonic()
                continue
            if reply.frames:
                break
        if busy_since is not None:
            served = bool(reply.frames) and reply.error_code() != ErrorCode.BUSY
            self.busy_log.append((frame.msg_type, time.monotonic() - busy_since, served))
        return reply
