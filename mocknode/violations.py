"""How the mock node breaks a requirement on purpose (``FaultSpec.violations``): the few
departures that need more than skipping a check in ``node.py`` or the modules of its commands."""
from __future__ import annotations

import struct
from dataclasses import dataclass

from protocol.cobs import cobs_encode
from protocol.crc import crc32c
from protocol.framing import HEADER, Frame, encode_frame
from protocol.messages import MESSAGE_CLASSES, Message, MessageError


@dataclass(frozen=True)
class StaleCrcFrame(Frame):
    """A cache replay sent with the CRC of the frame it replays (its header changed since)."""

    original_flags: int = 0
    original_seq: int = 0


def wire_bytes(frame: Frame) -> bytes:
    """The bytes a frame goes out as: ``encode_frame``, except for a :class:`StaleCrcFrame`."""
    if not isinstance(frame, StaleCrcFrame):
        return encode_frame(frame)
    payload = bytes(frame.payload)
    original = HEADER.pack(frame.version, frame.msg_type, frame.original_flags, 0, frame.original_seq,
                           frame.request_id) + payload
    body = HEADER.pack(frame.version, frame.msg_type, frame.flags, 0, frame.seq, frame.request_id) + payload
    return b"\x00" + cobs_encode(body + struct.pack("<I", crc32c(original))) + b"\x00"


def lenient_decode(msg_type: int, payload: bytes, version: int) -> Message:
    """Decode like a node that reads the fields it knows and ignores whatever follows them."""
    cls = MESSAGE_CLASSES[msg_type]
    for cut in range(len(payload), -1, -1):
        try:
            return cls.decode(payload[:cut], version)
        except MessageError:
            continue
    raise MessageError(f"{cls.__name__}: no prefix of the {len(payload)}-byte payload parses")
