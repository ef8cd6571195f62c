"""What the checks share: the session, the node's INFO, the checker's settings and records, and
the small steps most checks are made of (configure, acquire, read a transfer) with their
failures turned into :class:`Failure` lines."""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from nodecheck.outcomes import Failure, expect
from nodecheck.session import Reply, Session
from protocol.crc import crc32c
from protocol.framing import FLAG_LAST
from protocol.messages import (
    AcquireReply,
    AcquireRequest,
    BulkChunk,
    ConfigureReply,
    ConfigureRequest,
    ErrorCode,
    ErrorReply,
    InfoReply,
    Message,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
    TraceMeta,
)

M = TypeVar("M", bound=Message)
CHECK_AVERAGING = 4  # shots per checker acquisition: quick, and not the usual power-up default
CHECK_EXCITATION_HZ = 85e3
CHECK_CYCLES = 5
CHECK_SAMPLES = 3000  # per channel, at most max_samples: several chunks for the bulk checks


def describe(reply: Reply, timeout_s: float) -> str:
    """What a reply was, in words, for a failure line."""
    if not reply.frames:
        bad = f" ({len(reply.bad_frames)} bad frames: {reply.bad_frames[0]})" if reply.bad_frames else ""
        return f"no reply within {timeout_s:g} s{bad}"
    first = reply.first
    if first is None:
        return f"a {reply.frames[0].msg_type:#04x} frame that does not parse: {reply.parse_errors[0]}"
    if isinstance(first, ErrorReply):
        try:
            name = ErrorCode(first.code).name
        except ValueError:
            name = str(first.code)
        return f"ERROR {name} on {first.request_type:#04x} ({first.detail})"
    return type(first).__name__


@dataclass
class BulkRead:
    """One READ_* reply taken apart: its META, its chunks in arrival order, the joined data."""

    reply: Reply
    meta: Message
    chunks: list[BulkChunk]

    @property
    def data(self) -> bytes:
        return b"".join(c.data for c in sorted(self.chunks, key=lambda c: c.index))


@dataclass
class Record:
    """A measurement the checker made and read in full."""

    acquired: AcquireReply
    meta: TraceMeta
    data: bytes

    @property
    def codes(self) -> np.ndarray:
        n_channels = self.meta.channel_mask.bit_count()
        return np.frombuffer(self.data, dtype="<i2").reshape(n_channels, self.meta.count)


@dataclass
class Context:
    session: Session
    reboot: Callable[[], None] | None = None
    reboot_wait_s: float = 30.0
    info: InfoReply | None = None
    record: Record | None = None
    notes: dict[str, object] = field(default_factory=dict)  # what one check leaves for a later one

    @property
    def node(self) -> InfoReply:
        assert self.info is not None, "INFO is read before any check runs"
        return self.info

    @property
    def version(self) -> int:
        return self.session.version

    @property
    def timeout_s(self) -> float:
        return self.session.timing.timeout_s

    def has(self, capability: int) -> bool:
        return self.node.has(capability)

    @property
    def all_channels(self) -> int:
        return (1 << self.node.n_channels) - 1

    # ------------------------------------------------------------------ small steps
    def ask(self, message: Message, timeout_s: float | None = None, **frame_args) -> Reply:
        return self.session.command(message, timeout_s, **frame_args)

    def expect_message(self, reply: Reply, cls: type[M], what: str) -> M:
        first = reply.first
        if isinstance(first, cls):
            return first
        raise Failure(f"{what}: expected {cls.__name__}, got {describe(reply, self.timeout_s)}", reply.evidence())

    def expect_error(self, reply: Reply, code: ErrorCode, what: str) -> ErrorReply:
        first = reply.first
        if isinstance(first, ErrorReply) and first.code == code:
            return first
        raise Failure(f"{what}: expected ERROR {code.name}, got {describe(reply, self.timeout_s)}", reply.evidence())

    def settings(self) -> ConfigureRequest:
        """The checker's acquisition settings for this node."""
        n_samples = max(2, min(self.node.max_samples, CHECK_SAMPLES))
        return ConfigureRequest(CHECK_EXCITATION_HZ, CHECK_CYCLES, CHECK_AVERAGING, self.all_channels, n_samples)

    def configure(self, settings: ConfigureRequest | None = None) -> ConfigureReply:
        settings = settings or self.settings()
        return self.expect_message(self.ask(settings), ConfigureReply, "CONFIGURE with the checker's settings")

    def acquire(self, as_baseline: int = 0, averaging: int = CHECK_AVERAGING) -> AcquireReply:
        reply = self.ask(AcquireRequest(as_baseline), timeout_s=self.session.timing.acquire_s(averaging))
        return self.expect_message(reply, AcquireReply, f"ACQUIRE(as_baseline={as_baseline})")

    def status(self) -> StatusReply:
        return self.expect_message(self.ask(StatusRequest()), StatusReply, "STATUS")

    def read(self, request: Message, meta_type: type[M], what: str) -> BulkRead:
        """A READ_* request's reply: META first, then chunks; LAST on the last frame only."""
        reply = self.ask(request)
        meta = self.expect_message(reply, meta_type, what)
        chunks = []
        for i, (frame, message) in enumerate(zip(reply.frames, reply.messages, strict=True)):
            last = i == len(reply.frames) - 1
            expect(bool(frame.flags & FLAG_LAST) == last,
                   f"{what}: frame {i} of {len(reply.frames)} has LAST={'set' if not last else 'clear'}",
                   reply.evidence())
            if i:
                expect(isinstance(message, BulkChunk), f"{what}: frame {i} is not a BULK_CHUNK: "
                       f"{type(message).__name__}", reply.evidence())
                assert isinstance(message, BulkChunk)
                chunks.append(message)
        expect(reply.complete, f"{what}: the reply ended without a LAST frame ({describe(reply, self.timeout_s)})",
               reply.evidence())
        return BulkRead(reply, meta, chunks)

    def read_record(self, acquired: AcquireReply) -> Record:
        """READ_TRACES of a whole measurement, checked only as far as reassembly needs."""
        mask = acquired.channel_mask
        bulk = self.read(ReadTracesRequest(acquired.measurement_id, mask, 0, 0), TraceMeta,
                         f"READ_TRACES of measurement {acquired.measurement_id}")
        meta = bulk.meta
        assert isinstance(meta, TraceMeta)
        expect(crc32c(bulk.data) == meta.transfer_crc32c and len(bulk.data) == meta.total_bytes,
               f"READ_TRACES of measurement {acquired.measurement_id}: {len(bulk.data)} bytes with CRC "
               f"0x{crc32c(bulk.data):08X}, META says {meta.total_bytes} with 0x{meta.transfer_crc32c:08X}")
        return Record(acquired, meta, bulk.data)

    def ensure_record(self) -> Record:
        """A measurement taken with the checker's settings and read in full (made once; the checks
        that use it run right after R-TRACE-1, before acquisitions evict it from the node's RAM)."""
        if self.record is None:
            self.configure()
            self.record = self.read_record(self.acquire())
        return self.record


def same_f32(a: float | None, b: float | None) -> bool:
    """Equal as the float32 the wire carries."""
    if a is None or b is None:
        return a is b
    return math.isclose(float(np.float32(a)), float(np.float32(b)), rel_tol=0, abs_tol=0)
