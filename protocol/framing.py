"""Frames on the wire: ``0x00 COBS(header | payload | CRC-32C) 0x00``, and a streaming decoder.

Framing knows bytes, headers and CRCs only; the meaning of payloads lives in ``messages.py``.
All multi-byte fields are little-endian.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from protocol.cobs import CobsError, cobs_decode, cobs_encode, cobs_max_encoded_len
from protocol.crc import crc32c
from protocol.versions import PROTOCOL_VERSION

DELIMITER = 0x00

# version u8, msg_type u8, flags u8, reserved u8, seq u16, request_id u32
HEADER = struct.Struct("<BBBBHI")
HEADER_BYTES = HEADER.size  # 10
CRC_BYTES = 4
MAX_FRAME_BYTES = 4096  # decoded header + payload + CRC; fits two RX/TX buffers in node BRAM
MAX_PAYLOAD_BYTES = MAX_FRAME_BYTES - HEADER_BYTES - CRC_BYTES
MAX_ENCODED_BYTES = cobs_max_encoded_len(MAX_FRAME_BYTES)  # between two delimiters

FLAG_REPLY = 0x01  # sent by the node
FLAG_CACHED = 0x02  # reply replayed from the request-id cache (the command did not run again)
FLAG_LAST = 0x04  # last frame of a multi-frame reply


class FrameError(Exception):
    """A frame on the wire could not be accepted; the decoder reports it and goes on.

    ``raw`` holds the bytes found between the two delimiters (at most the first
    MAX_ENCODED_BYTES of an over-long run), for diagnostics.
    """

    raw: bytes = b""


class FrameCobsError(FrameError):
    """The bytes between two delimiters are not valid COBS."""


class FrameCrcError(FrameError):
    """The frame's CRC-32C does not match its contents."""


class FrameTooShort(FrameError):
    """Fewer bytes than a header plus CRC."""


class FrameTooLong(FrameError):
    """More bytes than MAX_FRAME_BYTES arrived without a delimiter; they were discarded."""


@dataclass(frozen=True)
class Frame:
    """One decoded frame: header fields and the raw payload."""

    msg_type: int
    request_id: int
    payload: bytes = b""
    flags: int = 0
    seq: int = 0
    version: int = PROTOCOL_VERSION

    @property
    def is_reply(self) -> bool:
        return bool(self.flags & FLAG_REPLY)


def encode_frame(frame: Frame) -> bytes:
    """Wire bytes of ``frame``, delimiter included; raises ValueError if it is too long."""
    if len(frame.payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    body = HEADER.pack(
        frame.version & 0xFF, frame.msg_type & 0xFF, frame.flags & 0xFF, 0,
        frame.seq & 0xFFFF, frame.request_id & 0xFFFFFFFF,
    ) + bytes(frame.payload)
    body += struct.pack("<I", crc32c(body))
    # A leading delimiter too: whatever noise preceded the frame is cut off at that 0x00.
    return b"\x00" + cobs_encode(body) + b"\x00"


def _error(cls: type[FrameError], message: str, raw: bytes) -> FrameError:
    error = cls(message)
    error.raw = raw
    return error


def decode_frame_body(block: bytes, max_frame_bytes: int = MAX_FRAME_BYTES) -> Frame:
    """Decode the bytes between two delimiters; raises a :class:`FrameError` subclass."""
    try:
        body = cobs_decode(block)
    except CobsError as exc:
        raise _error(FrameCobsError, str(exc), bytes(block)) from exc
    if len(body) < HEADER_BYTES + CRC_BYTES:
        raise _error(FrameTooShort, f"{len(body)} bytes is shorter than header + CRC", bytes(block))
    if len(body) > max_frame_bytes:
        raise _error(FrameTooLong, f"{len(body)} bytes exceeds MAX_FRAME_BYTES={max_frame_bytes}", bytes(block))
    (received,) = struct.unpack_from("<I", body, len(body) - CRC_BYTES)
    computed = crc32c(body[:-CRC_BYTES])
    if received != computed:
        raise _error(FrameCrcError, f"CRC-32C 0x{received:08X} != computed 0x{computed:08X}", bytes(block))
    version, msg_type, flags, _reserved, seq, request_id = HEADER.unpack_from(body)
    return Frame(msg_type=msg_type, request_id=request_id, payload=body[HEADER_BYTES:-CRC_BYTES],
                 flags=flags, seq=seq, version=version)


class FrameDecoder:
    """Streaming decoder: feed it any byte chunks, get frames and errors back in order.

    Memory is bounded by MAX_ENCODED_BYTES: an over-long run is discarded up to the next
    delimiter and reported once as :class:`FrameTooLong`. Empty runs (``00 00``) are idle
    fill and are ignored, which is how a receiver resynchronises after garbage.
    """

    def __init__(self, max_encoded_bytes: int = MAX_ENCODED_BYTES, max_frame_bytes: int = MAX_FRAME_BYTES) -> None:
        self._max = max_encoded_bytes
        self._max_frame = max_frame_bytes
        self._buffer = bytearray()
        self._discarding = False
        self.frames_ok = 0
        self.frames_bad = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame | FrameError]:
        """Consume ``data``; return complete frames and the errors of rejected ones."""
        out: list[Frame | FrameError] = []
        chunk = bytes(data)
        while chunk:
            cut = chunk.find(b"\x00")
            piece = chunk if cut < 0 else chunk[:cut]
            chunk = b"" if cut < 0 else chunk[cut + 1 :]
            if not self._discarding:
                self._buffer += piece
                if len(self._buffer) > self._max:
                    out.append(_error(FrameTooLong, f"no delimiter within {self._max} bytes; discarded",
                                      bytes(self._buffer[: self._max])))
                    self._buffer.clear()
                    self._discarding = True
                    self.frames_bad += 1
            if cut < 0:
                break
            if self._discarding:
                self._discarding = False
                continue
            if self._buffer:
                block = bytes(self._buffer)
                self._buffer.clear()
                try:
                    out.append(decode_frame_body(block, self._max_frame))
                    self.frames_ok += 1
                except FrameError as exc:
                    self.frames_bad += 1
                    out.append(exc)
        return out

    @property
    def buffered_bytes(self) -> int:
        """Bytes held while waiting for a delimiter (never above max_encoded_bytes)."""
        return len(self._buffer)
