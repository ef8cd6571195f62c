"""Checks of framing, versions and request handling: R-INFO-1, R-FRAME-*, R-VER-*, R-REQ-*."""
from __future__ import annotations

import math
import struct

from nodecheck.context import Context, describe
from nodecheck.outcomes import Failure, NotApplicable, expect
from nodecheck.session import hex_bytes
from protocol.cobs import cobs_encode
from protocol.crc import crc32c
from protocol.framing import FLAG_CACHED, FLAG_LAST, FLAG_REPLY, HEADER, MAX_FRAME_BYTES, MAX_PAYLOAD_BYTES
from protocol.messages import (
    ALL_CAPABILITIES,
    CAP_ON_BOARD_DI,
    AcquireRequest,
    ComputeDiRequest,
    ErrorCode,
    InfoReply,
    InfoRequest,
    MsgType,
    ReadDiRequest,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
)
from protocol.versions import PROTOCOL_VERSION

UNKNOWN_VERSION = 0x7F  # a header version no node speaks yet
_KNOWN_FLAGS = FLAG_REPLY | FLAG_CACHED | FLAG_LAST


def check_info(ctx: Context) -> str:
    info = ctx.node
    problems = []
    if not info.node_id:
        problems.append("node_id is empty")
    if info.max_frame_bytes != MAX_FRAME_BYTES:
        problems.append(f"max_frame_bytes {info.max_frame_bytes} != {MAX_FRAME_BYTES}")
    if not 0 < info.chunk_bytes <= MAX_PAYLOAD_BYTES - 4:
        problems.append(f"chunk_bytes {info.chunk_bytes} outside 1..{MAX_PAYLOAD_BYTES - 4}")
    if not 1 <= info.n_channels <= 32 or info.n_rx != info.n_channels or info.n_tx < 1:
        problems.append(f"n_channels {info.n_channels}, n_rx {info.n_rx}, n_tx {info.n_tx}")
    if info.capabilities & ~ALL_CAPABILITIES:
        problems.append(f"capabilities 0x{info.capabilities:X} has undefined bits")
    if info.boot_id == 0:
        problems.append("boot_id is 0")
    if not (math.isfinite(info.fs_hz) and info.fs_hz > 0) or info.max_samples < 2 or info.decimation < 1:
        problems.append(f"fs_hz {info.fs_hz}, max_samples {info.max_samples}, decimation {info.decimation}")
    if info.protocol_version != ctx.notes.get("info_frame_version"):
        problems.append(f"protocol_version {info.protocol_version} in a version {ctx.notes.get('info_frame_version')} "
                        "frame")
    if info.max_measurements < 2:
        problems.append(f"max_measurements {info.max_measurements}: no room for a baseline and a current")
    if ctx.version >= 2 and not (info.version_min is not None and info.version_max is not None
                                 and 1 <= info.version_min <= info.protocol_version <= info.version_max):
        problems.append(f"versions {info.version_min}..{info.version_max} do not contain {info.protocol_version}")
    expect(not problems, "; ".join(problems), ctx.notes.get("info_evidence", ""))  # type: ignore[arg-type]
    return f"{info.node_id}, firmware {info.firmware_version}, protocol {info.protocol_version}"


def check_frames(ctx: Context) -> None:
    for message in (StatusRequest(), InfoRequest(1, PROTOCOL_VERSION)):
        version = 1 if isinstance(message, InfoRequest) else None
        reply = ctx.session.command(message, version=version)
        expect(reply.frames, f"{type(message).__name__}: {describe(reply, ctx.timeout_s)}", reply.evidence())
        for i, frame in enumerate(reply.frames):
            expect(frame.flags & FLAG_REPLY, "a reply frame without the REPLY flag", reply.evidence())
            expect(not frame.flags & ~_KNOWN_FLAGS, f"flags 0x{frame.flags:02X} has undefined bits", reply.evidence())
            expect(bool(frame.flags & FLAG_LAST) == (i == len(reply.frames) - 1), "LAST not on the last frame only",
                   reply.evidence())
        expect(len(reply.frames) == 1, f"{len(reply.frames)} frames for a one-frame reply", reply.evidence())


def check_info_any_version(ctx: Context) -> str | NotApplicable:
    if ctx.node.version_max is None:
        return NotApplicable("a version-1 node: INFO in another header version gets BAD_VERSION there")
    cases = [(UNKNOWN_VERSION, 1, PROTOCOL_VERSION, min(PROTOCOL_VERSION, ctx.node.version_max)),
             (2, 1, 1, 1), (1, 1, UNKNOWN_VERSION, min(UNKNOWN_VERSION, ctx.node.version_max))]
    for header, host_min, host_max, expected in cases:
        reply = ctx.session.command(InfoRequest(host_min, host_max), version=header)
        info = ctx.expect_message(reply, InfoReply, f"INFO({host_min}..{host_max}) in header version {header}")
        expect(info.protocol_version == expected == reply.frames[0].version,
               f"INFO({host_min}..{host_max}) in header version {header}: answered in version "
               f"{reply.frames[0].version} announcing {info.protocol_version}, expected {expected}", reply.evidence())
    return "answered in versions 2 and 1 as asked"


def _next_measurement_id(ctx: Context) -> int:
    return ctx.acquire().measurement_id + 1


def check_bad_version(ctx: Context) -> None:
    status = ctx.session.command(StatusRequest(), version=UNKNOWN_VERSION)
    error = ctx.expect_error(status, ErrorCode.BAD_VERSION, f"STATUS in header version {UNKNOWN_VERSION}")
    version, lowest, newest = status.frames[0].version, ctx.node.version_min or 1, ctx.node.version_max or 1
    expect(lowest <= version <= newest, f"BAD_VERSION sent in header version {version}, not one the node speaks",
           status.evidence())
    expect(error.request_type == MsgType.STATUS, f"request_type {error.request_type:#04x} != 0x02", status.evidence())
    expected = _next_measurement_id(ctx)
    ctx.expect_error(ctx.session.command(AcquireRequest(0), version=UNKNOWN_VERSION), ErrorCode.BAD_VERSION,
                     f"ACQUIRE in header version {UNKNOWN_VERSION}")
    got = ctx.acquire().measurement_id
    expect(got == expected, f"the refused ACQUIRE ran: the next measurement is {got}, not {expected}")


def check_request_id_zero(ctx: Context) -> NotApplicable | None:
    if ctx.version < 2:
        return NotApplicable("version 1 does not define request id 0")
    expected = _next_measurement_id(ctx)
    ctx.expect_error(ctx.session.command(AcquireRequest(0), request_id=0), ErrorCode.MALFORMED,
                     "ACQUIRE with request_id 0")
    got = ctx.acquire().measurement_id
    expect(got == expected, f"the ACQUIRE with id 0 ran: the next measurement is {got}, not {expected}")
    return None


def check_unknown_command(ctx: Context) -> None:
    for msg_type in (0x0E, MsgType.INFO_REPLY, 0x42):
        reply = ctx.session.command(StatusRequest(), msg_type=msg_type, payload=b"")
        error = ctx.expect_error(reply, ErrorCode.UNKNOWN_COMMAND, f"msg_type {msg_type:#04x}")
        expect(error.request_type == msg_type, f"request_type {error.request_type:#04x} != {msg_type:#04x}",
               reply.evidence())


def _wrong_lengths(ctx: Context) -> list[tuple[str, int, bytes]]:
    reads = ReadTracesRequest(1, 1, 0, 0).encode(ctx.version)  # fixed part + n_wanted 0
    cases: list[tuple[str, int, bytes]] = [
        ("INFO + 1 byte", MsgType.INFO, InfoRequest(1, ctx.version).encode(1) + b"\x00"),
        ("STATUS + 1 byte", MsgType.STATUS, b"\x00"),
        ("CONFIGURE - 1 byte", MsgType.CONFIGURE, ctx.settings().encode(ctx.version)[:-1]),
        ("CONFIGURE + 1 byte", MsgType.CONFIGURE, ctx.settings().encode(ctx.version) + b"\x00"),
        ("ACQUIRE without its byte", MsgType.ACQUIRE, b""),
        ("ACQUIRE + 1 byte", MsgType.ACQUIRE, b"\x00\x00"),
        ("READ_TRACES without n_wanted", MsgType.READ_TRACES, reads[:-2]),
        ("READ_TRACES + 1 byte after n_wanted", MsgType.READ_TRACES, reads + b"\x00"),
        ("READ_TRACES n_wanted=2 with one index", MsgType.READ_TRACES, reads[:-2] + struct.pack("<HH", 2, 0)),
    ]
    if ctx.has(CAP_ON_BOARD_DI):
        di = ComputeDiRequest(1).encode(ctx.version)
        cases += [
            ("COMPUTE_DI - 1 byte", MsgType.COMPUTE_DI, di[:-1]),
            ("COMPUTE_DI + 1 byte", MsgType.COMPUTE_DI, di + b"\x00"),
            ("READ_DI without n_wanted", MsgType.READ_DI, ReadDiRequest(1).encode(ctx.version)[:-2]),
            ("READ_DI + 1 byte after n_wanted", MsgType.READ_DI, ReadDiRequest(1).encode(ctx.version) + b"\x00"),
        ]
    return cases


def check_lengths(ctx: Context) -> str:
    cases = _wrong_lengths(ctx)
    for what, msg_type, payload in cases:
        reply = ctx.session.command(StatusRequest(), msg_type=msg_type, payload=payload)
        ctx.expect_error(reply, ErrorCode.MALFORMED, f"{what} ({len(payload)} bytes)")
    ctx.configure()  # a node that took a wrong-length CONFIGURE has failed already; restore ours
    return f"{len(cases)} wrong lengths refused"


def _frame_errors(ctx: Context) -> tuple[int, int]:
    status = ctx.status()
    return status.crc_errors, status.framing_errors


def _expect_silence(ctx: Context, request_id: int, what: str) -> None:
    reply = ctx.session.collect({request_id}, ctx.timeout_s)[request_id]
    expect(not reply.frames, f"{what} was answered ({describe(reply, ctx.timeout_s)})", reply.evidence())


def check_corrupt_frame(ctx: Context) -> None:
    crc_before, _ = _frame_errors(ctx)
    frame = ctx.session.frame(StatusRequest())
    ctx.session.send_raw(ctx.session.wire_with_crc(frame, 0x00000001))
    _expect_silence(ctx, frame.request_id, "a STATUS frame with its CRC-32C off by one bit")
    crc_after, _ = _frame_errors(ctx)
    expect(crc_after > crc_before, f"crc_errors stayed at {crc_before} after a frame with a wrong CRC")


def oversized_wire(ctx: Context, request_id: int) -> bytes:
    """A STATUS frame with a valid CRC whose decoded size exceeds MAX_FRAME_BYTES."""
    body = HEADER.pack(ctx.version, MsgType.STATUS, 0, 0, 1, request_id) + b"\x55" * (MAX_PAYLOAD_BYTES + 20)
    return b"\x00" + cobs_encode(body + struct.pack("<I", crc32c(body))) + b"\x00"


def check_frame_sizes(ctx: Context) -> None:
    _, framing_before = _frame_errors(ctx)
    short = ctx.session.next_id()
    ctx.session.send_raw(b"\x00" + cobs_encode(b"\x01\x02\x03\x04\x05") + b"\x00")
    long_id = ctx.session.next_id()
    ctx.session.send_raw(oversized_wire(ctx, long_id))
    reply = ctx.session.collect({short, long_id}, ctx.timeout_s)[long_id]
    expect(not reply.frames, f"a {MAX_FRAME_BYTES + 20}-byte frame (valid CRC) was answered: "
           f"{describe(reply, ctx.timeout_s)}", reply.evidence())
    _, framing_after = _frame_errors(ctx)
    expect(framing_after >= framing_before + 2,
           f"framing_errors went from {framing_before} to {framing_after} after a 5-byte and an oversized frame")


def check_resync(ctx: Context) -> None:
    garbage = bytes((i * 37) % 255 + 1 for i in range(300))  # no 0x00 in it
    frame = ctx.session.frame(StatusRequest())
    ctx.session.send_raw(garbage)
    ctx.session.send_raw(b"\x00\x00\x00")
    reply = ctx.session.exchange(frame)
    status = reply.first
    if not isinstance(status, StatusReply):
        raise Failure(f"STATUS after 300 bytes of garbage and idle fill: {describe(reply, ctx.timeout_s)}",
                      hex_bytes(garbage[:16]))
