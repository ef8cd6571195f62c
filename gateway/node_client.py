"""Gateway side of the node protocol: one node's commands, with timeouts and capability checks.

INFO negotiates the protocol version (docs/protocol.md, 3.1): a version-1 node is spoken to in
version 1, and its records carry fewer of their own settings. A command the node's INFO does
not announce the capability for is refused before anything is sent. Underneath:
``frame_channel`` (frames over the serial transport, replies read per ``reply_decoding``),
``request_retries`` (bounded retries under one request id, ERROR BUSY), ``bulk_read`` (chunked,
CRC-32C-verified transfers) and ``node_transfers`` (what a transfer returns); the errors are in
``node_errors``.
"""
from __future__ import annotations

import random

from gateway.bulk_read import read_bulk
from gateway.frame_channel import FrameChannel
from gateway.node_errors import CapabilityMissing
from gateway.node_transfers import DiTransfer, TraceTransfer, di_transfer, mask_of, trace_transfer
from gateway.request_retries import RequestRetries
from imaging.grid import Grid
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    CAP_ON_BOARD_DI,
    CAPABILITY_NAMES,
    AcquireReply,
    AcquireRequest,
    ComputeDiReply,
    ComputeDiRequest,
    ConfigureReply,
    ConfigureRequest,
    DiMeta,
    InfoReply,
    InfoRequest,
    Message,
    ReadDiRequest,
    ReadTracesRequest,
    StatusReply,
    StatusRequest,
    TraceMeta,
)
from protocol.versions import OLDEST_VERSION, PROTOCOL_VERSION
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
        self.shot_period_s = shot_period_s
        self.compute_timeout_s = compute_timeout_s
        self.transfer_rounds = transfer_rounds
        rng = random.Random(seed)
        # Equal jitter: a retried command always leaves the node time to finish what it is doing.
        retry_backoff = Backoff(backoff_s, backoff_max_s, "equal")
        self._averaging = 1
        self._info: InfoReply | None = None
        self._channel = FrameChannel(url, baudrate=baudrate, exclusive=exclusive)
        self._requests = RequestRetries(self._channel, url, retries, retry_backoff, rng)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        self._channel.close()

    def reopen(self) -> None:
        """Open the port again after :class:`PortVanished` (e.g. a re-plugged USB-UART)."""
        self._channel.reopen()

    def __enter__(self) -> NodeClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # ------------------------------------------------------------------ session and counters
    @property
    def version(self) -> int | None:
        """The protocol version of this session, negotiated by :meth:`info` (None before)."""
        return self._channel.version

    @property
    def retries(self) -> int:
        return self._requests.retries

    @property
    def retry_backoff(self) -> Backoff:
        return self._requests.backoff

    @property
    def frame_errors(self) -> int:
        """Frames dropped: CRC or framing errors, and CRC-valid chunks that do not fit their transfer."""
        return self._channel.frame_errors

    @property
    def retried(self) -> int:
        """Commands sent again and chunks asked for again (lost, late or corrupt replies)."""
        return self._requests.retried

    @property
    def busy_replies(self) -> int:
        return self._requests.busy_replies

    # ------------------------------------------------------------------ commands
    def info(self) -> InfoReply:
        """HELLO/INFO: identity, capabilities and geometry, and the version this session speaks
        (the newest both sides speak); raises ProtocolMismatch if they share none."""
        self._channel.version = None
        self._info = None
        reply = self._command(InfoRequest(OLDEST_VERSION, PROTOCOL_VERSION), InfoReply)
        self._info = reply
        self._channel.version = reply.protocol_version
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

    def _command(self, request: Message, reply_type: type, timeout_s: float | None = None):
        """Send ``request`` until its reply arrives (see :class:`RequestRetries`)."""
        wait_s = timeout_s if timeout_s is not None else self.timeout_s
        return self._requests.command(request, reply_type, wait_s)

    def _bulk(self, make_request, meta_type: type):
        """A chunked transfer (see :func:`read_bulk`): (meta, data, chunks re-requested)."""
        chunk_retransmit = self._known_info().has(CAP_CHUNK_RETRANSMIT)
        return read_bulk(self._requests, make_request, meta_type, self.timeout_s, self.transfer_rounds,
                         chunk_retransmit)
