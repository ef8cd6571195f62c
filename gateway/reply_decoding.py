"""Which protocol version a node's reply is read in (pure; docs/protocol.md, 3.1).

A session speaks the version INFO negotiated. Before that (``session_version`` None) only
INFO_REPLY is expected, in any version the host speaks; an ERROR is read in any version,
its layout never changes. Anything else is a :class:`ProtocolMismatch`.
"""
from __future__ import annotations

from gateway.node_errors import ProtocolMismatch
from protocol.framing import Frame
from protocol.messages import InfoReply, Message, MessageError, MsgType, decode_message
from protocol.versions import OLDEST_VERSION, PROTOCOL_VERSION, SUPPORTED_VERSIONS


def decode_reply(frame: Frame, session_version: int | None) -> Message:
    """A reply in the session's version (ERROR in any: its layout never changes; INFO_REPLY in
    any the host speaks, the version it announces named in the mismatch otherwise)."""
    if frame.msg_type == MsgType.ERROR:
        version = frame.version
    elif session_version is None and frame.msg_type == MsgType.INFO_REPLY:
        if frame.version not in SUPPORTED_VERSIONS:
            try:
                announced = InfoReply.announced_version(frame.payload)
            except MessageError as exc:
                raise ProtocolMismatch(f"node answers INFO in protocol version {frame.version}: {exc}") from exc
            raise ProtocolMismatch(f"node speaks protocol version {announced}, host "
                                   f"{OLDEST_VERSION}..{PROTOCOL_VERSION}")
        version = frame.version
    elif frame.version != session_version:
        raise ProtocolMismatch(f"node frame has protocol version {frame.version}, session {session_version}")
    else:
        version = frame.version
    try:
        message = decode_message(frame.msg_type, frame.payload, version)
    except MessageError as exc:
        raise ProtocolMismatch(f"CRC-valid reply we cannot parse: {exc}") from exc
    if isinstance(message, InfoReply) and message.protocol_version != frame.version:
        raise ProtocolMismatch(f"INFO_REPLY announces version {message.protocol_version} in a version "
                               f"{frame.version} frame")
    return message
