"""The node's protocol state machine, pure: request frame in, reply frames out.

Implements docs/protocol.md exactly as the firmware should: version negotiation (it speaks
versions 1 and 2 and answers each request in the version of its header), the reply cache by
request id (``reply_cache.py``), capabilities, BUSY while an acquisition runs, and each
command on the node's state: its settings (``node_settings.py``), acquisitions
(``measuring.py``) kept in bounded RAM plus a baseline slot (``node_ram.py``), chunked bulk
replies (``bulk_replies.py``), the on-board DI map computed on decimated data
(``onboard_di.py``). A command refuses by raising ``refusal.Refused``. The scenario's
``violations`` make it break single requirements on purpose. Timing, line faults and reboots
belong to ``server.py``.
"""
from __future__ import annotations

import dataclasses
import random
import time
from collections.abc import Callable
from typing import ClassVar

import numpy as np

from imaging.dimap import BaselineMismatch
from imaging.grid import GridError
from imaging.measurement import Measurement, MeasurementError
from mocknode import measuring, physics
from mocknode.bulk_replies import CHUNK_BYTES, di_reply, trace_reply
from mocknode.faults import Violation
from mocknode.node_ram import MAX_CHANNELS, MAX_MEASUREMENTS, NodeRam, StoredMeasurement
from mocknode.node_settings import configured, configured_scenario, max_samples, power_up_settings
from mocknode.onboard_di import Decimation, GridRefused, decimated, onboard_map, requested_grid
from mocknode.recorded import RecordError, load_recorded_pipe
from mocknode.refusal import Refused
from mocknode.reply_cache import ReplyCache
from mocknode.scenario import NodeScenario
from mocknode.violations import StaleCrcFrame, lenient_decode
from protocol.framing import FLAG_CACHED, FLAG_LAST, FLAG_REPLY, MAX_FRAME_BYTES, Frame
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    CAP_ON_BOARD_DI,
    AcquireReply,
    AcquireRequest,
    ComputeDiReply,
    ComputeDiRequest,
    ConfigureReply,
    ConfigureRequest,
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
    UnknownMessageType,
    decode_message,
)
from protocol.versions import OLDEST_VERSION, PROTOCOL_VERSION, common_version

FIRMWARE_VERSION = (0, 4, 0)
SHOT_PERIOD_S = 0.005  # time per averaged shot (pulse repetition), for ACQUIRE's service time
SUPPLY_V = 5.0  # USB-powered Cmod A7
CAPABILITY_BITS = {"on_board_di": CAP_ON_BOARD_DI, "baseline_slot": CAP_BASELINE_SLOT,
                   "chunk_retransmit": CAP_CHUNK_RETRANSMIT}
_NEVER_BUSY = (MsgType.INFO, MsgType.STATUS)  # answered even while an acquisition runs
_REQUEST_TYPES = frozenset(range(MsgType.INFO, MsgType.READ_DI + 1))


class NodeSetupError(ValueError):
    """A scenario the node cannot represent on the wire (too many channels, long node id)."""


class MockNode:
    """One simulated FPGA node; ``clock()`` gives seconds (monotonic)."""

    def __init__(self, scenario: NodeScenario, clock: Callable[[], float] = time.monotonic) -> None:
        n_rx = len(scenario.rings.rx_angles)
        if n_rx > MAX_CHANNELS:
            raise NodeSetupError(f"{scenario.node_id}: {n_rx} receivers exceed the {MAX_CHANNELS}-bit channel mask")
        if len(scenario.node_id.encode("utf-8")) > 32:
            raise NodeSetupError(f"node id {scenario.node_id!r} is longer than 32 bytes")
        try:  # a node replaying full-wave records reads them once, here
            self._recorded = load_recorded_pipe(scenario) if scenario.fullwave is not None else None
        except RecordError as exc:
            raise NodeSetupError(str(exc)) from exc
        self.scenario = scenario
        self.clock = clock
        self._epoch = clock()  # scenario time 0: defects grow and temperature drifts from here
        self._rng = np.random.default_rng(scenario.seed)
        self._boot_rng = random.Random(scenario.seed ^ 0x5EED)
        self._fault_rng = random.Random(scenario.seed ^ 0xFA17)
        only = scenario.faults.protocol_version
        self.version_min, self.version_max = (only, only) if only else (OLDEST_VERSION, PROTOCOL_VERSION)
        self.capabilities = sum(CAPABILITY_BITS[name] for name in set(scenario.firmware.capabilities))
        self.violations = frozenset(scenario.faults.violations)
        self.crc_errors = 0
        self.framing_errors = 0
        self.boot_id = 0
        self.boot()

    @property
    def protocol_version(self) -> int:
        """The newest version the node speaks."""
        return self.version_max

    # ------------------------------------------------------------------ power
    def boot(self) -> None:
        """Power-up (or reboot): every RAM state is lost, a new boot id is drawn, and the
        power-up settings are in force again."""
        if not (self.boot_id and Violation.BOOT_ID_STICKY in self.violations):
            self.boot_id = self._boot_rng.randrange(1, 2**32)
        self._boot_time = self.clock()
        self._seq = 0
        self._ram = NodeRam()
        self._cache = ReplyCache()
        self._busy_until = 0.0
        self._running: tuple[int, int, int, bytes] | None = None  # the acquisition in progress
        self._stuck_busy = False
        self.rejected_requests = 0
        self.last_service_s = 0.0
        self.config = self.power_up_settings()

    def power_up_settings(self) -> ConfigureReply:
        """The settings in force after a boot: the scenario's ``power_up`` keys, else its own."""
        return power_up_settings(self.scenario)

    @property
    def busy(self) -> bool:
        return self._stuck_busy or self.clock() < self._busy_until

    def stored_codes(self, measurement_id: int) -> np.ndarray | None:
        """A copy of a stored measurement's codes [n_enabled_channels, n] (an oracle for tests)."""
        stored = self._ram.find(measurement_id)
        return None if stored is None else stored.acquisition.codes.copy()

    def note_frame_error(self, crc: bool) -> None:
        """The server's decoder rejected a frame (counted in STATUS)."""
        if crc:
            self.crc_errors += 1
        else:
            self.framing_errors += 1

    # ------------------------------------------------------------------ dispatch
    def speaks(self, version: int) -> bool:
        return self.version_min <= version <= self.version_max

    def handle(self, request: Frame) -> list[Frame]:
        """Reply frames for one request frame (empty for frames that are not requests, and for a
        resend of the acquisition still running: its reply follows when it is done)."""
        self.last_service_s = 0.0
        if request.is_reply:
            return []
        versioned = self.version_max >= 2  # version 2's rules: INFO always answered, request id 0 refused
        version = request.version if self.speaks(request.version) else self.version_max
        if versioned and request.request_id == 0 and Violation.REQUEST_ID_ZERO_RUNS not in self.violations:
            return self._error(request, ErrorCode.MALFORMED, "request id 0 is reserved", version)
        if versioned and request.msg_type == MsgType.INFO and (
            self.speaks(request.version) or Violation.INFO_NEEDS_VERSION not in self.violations
        ):
            return self._hello(request)
        if not self.speaks(request.version):
            if Violation.VERSION_IGNORED in self.violations:
                version = min(max(request.version, OLDEST_VERSION), PROTOCOL_VERSION)
            else:
                return self._error(request, ErrorCode.BAD_VERSION,
                                   f"node speaks versions {self.version_min}..{self.version_max}", version)
        busy = self._busy_answer(request, version)
        if busy is not None:
            return busy
        cached = self._cache.get(request, version)
        if cached is not None and not (
            request.msg_type == MsgType.ACQUIRE and Violation.ACQUIRES_TWICE in self.violations
        ):
            return [self._replay(f) for f in cached]
        if request.msg_type not in _REQUEST_TYPES:
            return self._error(request, ErrorCode.UNKNOWN_COMMAND, f"0x{request.msg_type:02X} is not a request",
                               version)
        if request.msg_type in (MsgType.COMPUTE_DI, MsgType.READ_DI) and not self.capabilities & CAP_ON_BOARD_DI:
            return self._error(request, ErrorCode.UNKNOWN_COMMAND, "no on-board DI (capability ON_BOARD_DI absent)",
                               version)
        try:
            message = self._decode(request, version)
        except UnknownMessageType as exc:
            return self._error(request, ErrorCode.UNKNOWN_COMMAND, str(exc), version)
        except MessageError as exc:
            return self._error(request, ErrorCode.MALFORMED, str(exc), version)
        handler = self._HANDLERS.get(type(message))
        if handler is None:
            return self._error(request, ErrorCode.UNKNOWN_COMMAND, f"{type(message).__name__} is not a request",
                               version)
        try:
            replies = handler(self, message)
            frames = self._frames(request, replies, version)
        except Refused as refused:
            frames = self._error(request, refused.code, refused.detail, version)
        except (physics.PhysicsError, MeasurementError, GridError) as exc:
            # The simulated hardware failed: answer like firmware would, keep serving.
            frames = self._error(request, ErrorCode.HARDWARE_FAULT, f"{type(exc).__name__}: {exc}", version)
        refused_now = frames[0].msg_type == MsgType.ERROR
        if isinstance(message, (ConfigureRequest, AcquireRequest, ComputeDiRequest)) and (
            not refused_now or Violation.CACHES_ERRORS in self.violations
        ):
            self._cache.put(request, version, frames)
        if isinstance(message, AcquireRequest) and not refused_now and self.scenario.firmware.busy_while_acquiring:
            self._busy_until = self.clock() + self.last_service_s
            self._running = (version, request.request_id, request.msg_type, request.payload)
        return frames

    def _decode(self, request: Frame, version: int) -> Message:
        try:
            return decode_message(request.msg_type, request.payload, version)
        except UnknownMessageType:
            raise
        except MessageError:
            if Violation.LENIENT_LENGTHS not in self.violations:
                raise
            return lenient_decode(request.msg_type, request.payload, version)

    def _busy_answer(self, request: Frame, version: int) -> list[Frame] | None:
        """ERROR BUSY (or nothing, for a resend of the running acquisition) while the node works."""
        if request.msg_type in _NEVER_BUSY:
            return None
        if self._stuck_busy:
            return self._error(request, ErrorCode.BUSY, "busy", version)
        if self.clock() < self._busy_until:
            if self._running == (version, request.request_id, request.msg_type, request.payload):
                return []
            self._stuck_busy = Violation.BUSY_FOREVER in self.violations
            return self._error(request, ErrorCode.BUSY, "acquisition in progress", version)
        p = self.scenario.faults.busy_probability
        if p and self._fault_rng.random() < p:
            return self._error(request, ErrorCode.BUSY, "bus in use", version)
        return None

    def _replay(self, frame: Frame) -> Frame:
        seq = self._next_seq()
        if Violation.CACHED_CRC_STALE in self.violations:
            return StaleCrcFrame(frame.msg_type, frame.request_id, frame.payload, frame.flags | FLAG_CACHED, seq,
                                 frame.version, original_flags=frame.flags, original_seq=frame.seq)
        return dataclasses.replace(frame, flags=frame.flags | FLAG_CACHED, seq=seq)

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def _frames(self, request: Frame, replies: list[Message], version: int) -> list[Frame]:
        layout = min(version, PROTOCOL_VERSION)  # a node of a future version: our newest layouts
        encoded = [message.encode(layout) for message in replies]  # a field that does not fit refuses them all
        frames = []
        for i, (message, payload) in enumerate(zip(replies, encoded, strict=True)):
            flags = FLAG_REPLY | (FLAG_LAST if i == len(replies) - 1 else 0)
            frames.append(Frame(message.TYPE, request.request_id, payload, flags, self._next_seq(), version))
        return frames

    def _error(self, request: Frame, code: ErrorCode, detail: str, version: int) -> list[Frame]:
        self.rejected_requests += 1
        return self._frames(request, [ErrorReply(int(code), request.msg_type & 0xFF, detail)], version)

    def _hello(self, request: Frame) -> list[Frame]:
        """INFO in whatever header version: answered in the newest version both sides speak."""
        try:
            hello = InfoRequest.decode(request.payload, OLDEST_VERSION)  # its layout never changes
        except MessageError as exc:
            return self._error(request, ErrorCode.MALFORMED, str(exc), self.version_max)
        version = common_version(hello.host_version_min, hello.host_version_max, self.version_min, self.version_max)
        version = version or self.version_max  # no common version: the host learns ours and stops
        return self._frames(request, self._info(version), version)

    # ------------------------------------------------------------------ commands
    def _info(self, version: int) -> list[Message]:
        scn = self.scenario
        tx, rx = tuple(scn.rings.tx_angles), tuple(scn.rings.rx_angles)
        return [InfoReply(
            scn.node_id, *FIRMWARE_VERSION, version, self.capabilities, self.boot_id, MAX_FRAME_BYTES,
            CHUNK_BYTES, len(rx), scn.acquisition.adc_bits, scn.acquisition.decimation, MAX_MEASUREMENTS,
            float(scn.acquisition.fs_hz), max_samples(scn, self._recorded), float(scn.rings.tx_rx_distance_mm),
            float(scn.pipe.outer_circumference_mm), float(scn.pipe.velocity_m_s), len(tx), len(rx), tx, rx,
            self.version_min, min(self.version_max, 255),
        )]

    def _info_request(self, message: InfoRequest) -> list[Message]:
        return self._info(self.version_max)  # a version-1 node: INFO in its own version

    def _status(self, message: StatusRequest) -> list[Message]:
        last = self._ram.latest()
        idle = self._recorded.baseline.temperature_c if self._recorded else self.scenario.temperature.mean_c
        temperature = last.acquisition.temperature_c if last else idle
        return [StatusReply(
            int(self.clock() - self._boot_time), self.boot_id, float(temperature), SUPPLY_V,
            self.crc_errors, self.framing_errors, self.rejected_requests, self._ram.baseline_id,
            len(self._ram), int(self.busy),
        )]

    def _configure(self, message: ConfigureRequest) -> list[Message]:
        self.config = configured(message, self.scenario, self._recorded, Violation.CLAMPS_SETTINGS in self.violations)
        return [self.config]

    def _acquire(self, message: AcquireRequest) -> list[Message]:
        if message.as_baseline and not self.capabilities & CAP_BASELINE_SLOT:
            raise Refused(ErrorCode.BAD_ARGUMENT, "no baseline slot (capability BASELINE_SLOT absent)")
        scn = configured_scenario(self.scenario, self.config)
        elapsed_s = self.clock() - self._epoch
        acquisition, full = measuring.acquire(scn, self.config.channel_mask, self._recorded, elapsed_s, self._rng)
        stored = self._ram.store(bool(message.as_baseline), self.config, acquisition, full)
        self.last_service_s = self.config.averaging * SHOT_PERIOD_S
        cfg = self.config
        return [AcquireReply(stored.measurement_id, int(stored.is_baseline), float(acquisition.temperature_c),
                             cfg.channel_mask, cfg.n_samples, int(self.clock() - self._boot_time), self.boot_id,
                             cfg.excitation_hz, cfg.cycles, cfg.averaging, float(acquisition.fs_hz))]

    def _read_traces(self, message: ReadTracesRequest) -> list[Message]:
        stored = self._ram.measurement(message.measurement_id)
        return trace_reply(message, stored, self.boot_id, self.scenario.acquisition.adc_bits,
                           bool(self.capabilities & CAP_CHUNK_RETRANSMIT), self.violations)

    def _decimated(self, stored: StoredMeasurement, factor: int) -> Measurement:
        method: Decimation = "boxcar" if Violation.DI_BOXCAR_DECIMATION in self.violations else "subsample"
        return decimated(stored.measurement, stored.acquisition.codes, stored.acquisition.volts_per_code, factor,
                         method)

    def _compute_di(self, message: ComputeDiRequest) -> list[Message]:
        baseline_id = message.baseline_id or self._ram.baseline_id
        if baseline_id == 0:
            raise Refused(ErrorCode.NO_BASELINE, "no baseline stored")
        baseline, current = self._ram.measurement(baseline_id), self._ram.measurement(message.current_id)
        factor = message.decimation or self.scenario.acquisition.decimation
        if not 1 <= factor <= 100:
            raise Refused(ErrorCode.BAD_ARGUMENT, "decimation outside 1..100")
        try:
            grid = requested_grid(message, self.scenario.rings.tx_rx_distance_mm)
            pixels, peak = onboard_map(self._decimated(baseline, factor), self._decimated(current, factor), grid)
        except GridRefused as exc:
            raise Refused(ErrorCode.BAD_ARGUMENT, str(exc)) from exc
        except BaselineMismatch as exc:
            raise Refused(ErrorCode.BAD_ARGUMENT, f"baseline mismatch: {exc}") from exc
        reply = ComputeDiReply(
            self._ram.next_di_id, current.measurement_id, baseline.measurement_id, factor, grid.axial_count,
            grid.angle_count, float(pixels[peak]), float(grid.axial_mm[peak[0]]), float(grid.angle_deg[peak[1]]),
        )
        self._ram.store_di(reply, grid, pixels)
        return [reply]

    def _read_di(self, message: ReadDiRequest) -> list[Message]:
        stored = self._ram.di_map(message.di_id)
        return di_reply(message, stored, self.boot_id, bool(self.capabilities & CAP_CHUNK_RETRANSMIT), self.violations)

    _HANDLERS: ClassVar[dict[type, Callable]] = {
        InfoRequest: _info_request,
        StatusRequest: _status,
        ConfigureRequest: _configure,
        AcquireRequest: _acquire,
        ReadTracesRequest: _read_traces,
        ComputeDiRequest: _compute_di,
        ReadDiRequest: _read_di,
    }
