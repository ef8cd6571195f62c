"""Gateway side of the node protocol: commands with timeouts, bounded retries and verified transfers.

A retried command reuses its request id, so the node answers a repeat from its reply cache
instead of running it twice (no double acquisition); ERROR BUSY is retried the same way, bulk
reads included. Bulk replies are reassembled from chunks; only lost chunks are asked for again
(the whole transfer from a node without CHUNK_RETRANSMIT); the whole transfer is checked
against its CRC-32C. INFO negotiates the protocol version (docs/protocol.md, 3.1): a version-1
node is spoken to in version 1, and its records carry fewer of their own settings. The errors
are in ``gateway.node_errors``; what a transfer returns, in ``gateway.node_transfers``.
"""
from __future__ import annotations

import random
import time
from typing import Any

from gateway.node_errors import (
    CapabilityMissing,
    NodeError,
    NodeRebooted,
    NodeTimeout,
    ProtocolMismatch,
    TransferError,
)
from gateway.node_transfers import DiTransfer, TraceTransfer, di_transfer, mask_of, trace_transfer
from imaging.grid import Grid
from nodelink.transport import SerialTransport
from protocol.bulk import BulkAssembler, BulkError, TransferCrcError
from protocol.framing import FLAG_LAST, Frame, FrameDecoder, FrameError, encode_frame
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    CAP_ON_BOARD_DI,
    CAPABILITY_NAMES,
    MAX_CHUNK_LIST,
    AcquireReply,
    AcquireRequest,
    BulkChunk,
    ComputeDiReply,
    ComputeDiRequest,
    ConfigureReply,
    ConfigureRequest,
    DiMeta,
    ErrorCode,
    ErrorReply,
    InfoReply,
    InfoRequest,
    Message,
    MessageError,
    MsgType,
    ReadDiRequest,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
    TraceMeta,
    decode_message,
)
from protocol.versions import HELLO_VERSION, OLDEST_VERSION, PROTOCOL_VERSION, SUPPORTED_VERSIONS
from retry_timing.backoff import Backoff


class NodeClient:
    """Talks to one node over ``serial.serial_for_url(url)``: a device path, socket://, loop://."""

    def __init__(
        self,
        url: str,
        baudrate: int = 230400,
        timeout_s: float = 1.0,
        retries: int = 3,
        backoff_s: float = 0.05,
        backoff_max_s: float = 2.0,
        shot_period_s: float = 0.01,
        compute_timeout_s: float = 60.0,
        transfer_rounds: int = 4,
        exclusive: bool = True,
        seed: int | None = None,
    ) -> None:
        self.url = url
        self.timeout_s = timeout_s
        self.retries = retries
        # Equal jitter: a retried command always leaves the node time to finish what it is doing.
        self.retry_backoff = Backoff(backoff_s, backoff_max_s, "equal")
        self.shot_period_s = shot_period_s
        self.compute_timeout_s = compute_timeout_s
        self.transfer_rounds = transfer_rounds
        self._rng = random.Random(seed)
        # A random first id: a restarted gateway must not hit the node's cache of an old session.
        self._request_id = self._rng.randrange(1, 2**32)
        self._seq = 0
        self._averaging = 1
        self._info: InfoReply | None = None
        self.version: int | None = None  # negotiated by info()
        self.frame_errors = 0
        self.retried = 0  # commands sent again and chunks asked for again (lost, late or corrupt replies)
        self.busy_replies = 0
        self._decoder = FrameDecoder()
        self._transport = SerialTransport(url, baudrate=baudrate, exclusive=exclusive)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        self._transport.close()

    def reopen(self) -> None:
        """Open the port again after :class:`PortVanished` (e.g. a re-plugged USB-UART)."""
        self._transport.reopen()
        self._decoder = FrameDecoder()

    def __enter__(self) -> NodeClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ------------------------------------------------------------------ commands
    def info(self) -> InfoReply:
        """HELLO/INFO: identity, capabilities and geometry, and the version this session speaks
        (the newest both sides speak); raises ProtocolMismatch if they share none."""
        self.version = None
        self._info = None
        reply = self._command(InfoRequest(OLDEST_VERSION, PROTOCOL_VERSION), InfoReply)
        self._info = reply
        self.version = reply.protocol_version
        return reply

    @property
    def known_info(self) -> InfoReply | None:
        """The last INFO reply of this session (None before the first)."""
        return self._info

    def status(self) -> StatusReply:
        self._known_info()
        return self._command(StatusRequest(), StatusReply)

    def configure(
        self, excitation_hz: float, cycles: int, averaging: int, n_samples: int,
        channels: tuple[int, ...] | list[int] | None = None,
    ) -> ConfigureReply:
        """Set excitation and acquisition; returns what the node applied."""
        mask = mask_of(channels, self._known_info().n_channels)
        reply = self._command(ConfigureRequest(excitation_hz, cycles, averaging, mask, n_samples), ConfigureReply)
        self._averaging = reply.averaging
        return reply

    def acquire(self, baseline: bool, timeout_s: float | None = None) -> AcquireReply:
        """Fire and record (averaged); a retry returns the cached reply, never a second acquisition.
        ``baseline`` also fills the node's baseline slot (capability BASELINE_SLOT)."""
        if baseline:
            self._require(CAP_BASELINE_SLOT)
        else:
            self._known_info()
        wait_s = timeout_s if timeout_s is not None else self.timeout_s + self._averaging * self.shot_period_s
        return self._command(AcquireRequest(int(baseline)), AcquireReply, timeout_s=wait_s)

    def compute_di(
        self, current_id: int, baseline_id: int = 0, decimation: int = 0, grid: Grid | None = None,
        timeout_s: float | None = None,
    ) -> ComputeDiReply:
        """On-board DI map of ``current_id`` against ``baseline_id`` (0: the stored baseline)."""
        self._require(CAP_ON_BOARD_DI)
        spec = (grid.axial_start_mm, grid.axial_step_mm, grid.axial_count,
                grid.angle_start_deg, grid.angle_step_deg, grid.angle_count) if grid else (0.0, 0.0, 0, 0.0, 0.0, 0)
        request = ComputeDiRequest(current_id, baseline_id, decimation, *spec)
        return self._command(request, ComputeDiReply, timeout_s=timeout_s or self.compute_timeout_s)

    def read_traces(
        self, measurement_id: int, channels: tuple[int, ...] | list[int] | None = None,
        start: int = 0, count: int | None = None,
    ) -> TraceTransfer:
        """Raw int16 codes [n_channels, n] of one measurement, CRC-32C verified."""
        mask = mask_of(channels, self._known_info().n_channels)

        def request(chunks: tuple[int, ...]) -> ReadTracesRequest:
            return ReadTracesRequest(measurement_id, mask, start, count or 0, chunks)

        return trace_transfer(*self._bulk(request, TraceMeta))

    def read_di(self, di_id: int) -> DiTransfer:
        """Pixels float32 [n_axial, n_angle] of an on-board DI map, CRC-32C verified."""
        self._require(CAP_ON_BOARD_DI)
        return di_transfer(*self._bulk(lambda chunks: ReadDiRequest(di_id, chunks), DiMeta))

    # ------------------------------------------------------------------ machinery
    def _known_info(self) -> InfoReply:
        return self._info if self._info is not None else self.info()

    def _require(self, capability: int) -> None:
        info = self._known_info()
        if not info.has(capability):
            raise CapabilityMissing(f"node {info.node_id} lacks capability {CAPABILITY_NAMES[capability]}")

    def _next_request_id(self) -> int:
        self._request_id = self._request_id % (2**32 - 1) + 1  # never 0
        return self._request_id

    def _send(self, message: Message, request_id: int) -> None:
        self._seq = (self._seq + 1) & 0xFFFF
        version = HELLO_VERSION if self.version is None else self.version  # INFO goes out in version 1
        frame = Frame(message.TYPE, request_id, message.encode(version), seq=self._seq, version=version)
        self._transport.write(encode_frame(frame))

    def _backoff(self, attempt: int) -> None:
        time.sleep(self.retry_backoff.delay_s(attempt, self._rng))

    def _replies(self, request_id: int, timeout_s: float):
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
                message = self._decode_reply(item)
                if isinstance(message, ErrorReply) and message.code == ErrorCode.BAD_VERSION:
                    raise ProtocolMismatch(f"node refused protocol version {self.version or HELLO_VERSION}: "
                                           f"{message.detail}")
                yield item, message
                deadline = time.monotonic() + timeout_s

    def _decode_reply(self, frame: Frame) -> Message:
        """A reply in the session's version (ERROR in any: its layout never changes; INFO_REPLY in
        any the host speaks, the version it announces named in the mismatch otherwise)."""
        if frame.msg_type == MsgType.ERROR:
            version = frame.version
        elif self.version is None and frame.msg_type == MsgType.INFO_REPLY:
            if frame.version not in SUPPORTED_VERSIONS:
                try:
                    announced = InfoReply.announced_version(frame.payload)
                except MessageError as exc:
                    raise ProtocolMismatch(f"node answers INFO in protocol version {frame.version}: {exc}") from exc
                raise ProtocolMismatch(f"node speaks protocol version {announced}, host "
                                       f"{OLDEST_VERSION}..{PROTOCOL_VERSION}")
            version = frame.version
        elif frame.version != self.version:
            raise ProtocolMismatch(f"node frame has protocol version {frame.version}, session {self.version}")
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

    def _attempts(self, request: Message, wait_s: float):
        """Send ``request`` and yield, per attempt, an iterator over its replies; resend it with the
        SAME request id (after a backoff) when the caller asks for the next attempt, i.e. after a
        timeout or an ERROR BUSY, until the retries run out (NodeTimeout)."""
        request_id = self._next_request_id()
        busy_before = self.busy_replies
        for attempt in range(self.retries + 1):
            if attempt:
                self.retried += 1
                self._backoff(attempt)
            self._send(request, request_id)
            yield self._answers(request_id, wait_s)
        busy = self.busy_replies - busy_before
        outcome = f"BUSY {busy} times, no reply the other {self.retries + 1 - busy}" if busy else "no reply"
        raise NodeTimeout(
            f"{type(request).__name__} to {self.url}: {outcome} in {self.retries + 1} attempts of {wait_s:.2f} s"
        )

    def _answers(self, request_id: int, wait_s: float):
        """The replies to one attempt; ends at a timeout or an ERROR BUSY; any other ERROR is a NodeError."""
        for frame, message in self._replies(request_id, wait_s):
            if isinstance(message, ErrorReply):
                if message.code == ErrorCode.BUSY:
                    self.busy_replies += 1
                    return  # asked again after the backoff, like a timeout
                raise NodeError(message.code, message.detail, message.request_type)
            yield frame, message

    def _command(self, request: Message, reply_type: type, timeout_s: float | None = None):
        """Send ``request`` until its reply arrives (see ``_attempts``)."""
        wait_s = timeout_s if timeout_s is not None else self.timeout_s
        for answers in self._attempts(request, wait_s):
            for _frame, message in answers:
                if isinstance(message, reply_type):
                    return message
                raise ProtocolMismatch(f"expected {reply_type.__name__}, got {type(message).__name__}")
        raise AssertionError("unreachable: _attempts ends in NodeTimeout")

    def _collect(self, request: Message, meta_type: type, pending: dict[int, BulkChunk]):
        """One request of a bulk read; returns its *_META, chunks into ``pending``. An attempt ends
        at the LAST frame or when no frame came for ``timeout_s`` (lost chunks are asked for later)."""
        meta = None
        for answers in self._attempts(request, self.timeout_s):
            for frame, message in answers:
                if isinstance(message, meta_type):
                    meta = message
                elif isinstance(message, BulkChunk):
                    pending[message.index] = message
                else:
                    raise ProtocolMismatch(f"unexpected {type(message).__name__} in a bulk reply")
                if frame.flags & FLAG_LAST:
                    break
            if meta is not None:
                return meta
        raise AssertionError("unreachable: _attempts ends in NodeTimeout")

    def _bulk(self, make_request, meta_type: type):
        """Read a chunked transfer; re-request only missing chunks; verify the whole-transfer CRC."""
        rerequested = 0
        first: Any = None  # the transfer's first meta reply (ReadTracesMeta or ReadDiMeta, both carry boot_id)
        crc_failures = 0
        wanted: tuple[int, ...] = ()
        assembler: BulkAssembler | None = None
        for _round in range(self.transfer_rounds + 1):
            pending: dict[int, BulkChunk] = {}
            meta = self._collect(make_request(wanted), meta_type, pending)
            if first is None:
                first = meta
            elif meta.boot_id != first.boot_id:
                raise NodeRebooted(f"node rebooted during the transfer (boot id {first.boot_id} -> {meta.boot_id})")
            elif meta != first:
                raise TransferError(f"the node announced a different transfer: {meta} != {first}")
            if assembler is None:
                try:
                    assembler = BulkAssembler(meta.total_bytes, meta.chunk_bytes, meta.n_chunks, meta.transfer_crc32c)
                except BulkError as exc:
                    raise ProtocolMismatch(str(exc)) from exc
            for chunk in pending.values():
                try:
                    assembler.add(chunk)
                except BulkError:
                    self.frame_errors += 1  # a CRC-valid chunk that does not fit: drop and ask again
            missing = assembler.missing()
            if missing and not self._known_info().has(CAP_CHUNK_RETRANSMIT):
                wanted = ()  # the node sends whole transfers only: read it all again, keep what arrived
                rerequested += len(missing)
                self.retried += len(missing)
                continue
            if not missing:
                try:
                    return meta, assembler.result(), rerequested
                except TransferCrcError as exc:
                    crc_failures += 1
                    if crc_failures > 1:
                        raise TransferError(f"{exc} (after re-reading the whole transfer)") from exc
                    assembler, wanted = None, ()
                    self.retried += meta.n_chunks  # every chunk is read again
                    continue
            wanted = tuple(missing[:MAX_CHUNK_LIST])
            rerequested += len(wanted)
            self.retried += len(wanted)  # chunks sent again count as retries (the metric says so)
        raise TransferError(f"{type(first).__name__}: chunks still missing after {self.transfer_rounds} rounds")
