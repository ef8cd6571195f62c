"""The node's protocol state machine, pure: request frame in, reply frames out.

Implements docs/protocol.md exactly as the firmware should: version negotiation (it speaks
versions 1 and 2 and answers each request in the version of its header), the reply cache by
request id, a few measurements in bounded RAM plus a baseline slot, chunked bulk replies, the
on-board DI map computed on decimated data, capabilities, BUSY while an acquisition runs. The
scenario's ``violations`` make it break single requirements on purpose. Timing, line faults
and reboots belong to ``server.py``.
"""
from __future__ import annotations

import dataclasses
import math
import random
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from imaging.dimap import BaselineMismatch
from imaging.grid import Grid, GridError
from imaging.measurement import Measurement, MeasurementError
from mocknode import physics
from mocknode.faults import Violation
from mocknode.onboard_di import Decimation, GridRefused, decimated, onboard_map, requested_grid
from mocknode.recorded import RecordError, acquire_recorded, load_recorded_pipe
from mocknode.scenario import NodeScenario
from mocknode.violations import StaleCrcFrame, lenient_decode
from protocol.bulk import n_chunks_for, split_chunks
from protocol.crc import crc32c
from protocol.framing import FLAG_CACHED, FLAG_LAST, FLAG_REPLY, MAX_FRAME_BYTES, Frame
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    CAP_ON_BOARD_DI,
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
    UnknownMessageType,
    decode_message,
)
from protocol.versions import OLDEST_VERSION, PROTOCOL_VERSION, common_version

FIRMWARE_VERSION = (0, 4, 0)
CHUNK_BYTES = 2048  # bulk payload per frame: 98 % wire efficiency, 4 KiB frame buffers
MAX_MEASUREMENTS = 4  # RAM slots, the baseline included (4 x 96 KB of the 512 KB SRAM)
MAX_DI_MAPS = 2
MAX_CHANNELS = 32  # the channel mask is 32 bits wide
REPLY_CACHE_SIZE = 16
SHOT_PERIOD_S = 0.005  # time per averaged shot (pulse repetition), for ACQUIRE's service time
SUPPLY_V = 5.0  # USB-powered Cmod A7
CAPABILITY_BITS = {"on_board_di": CAP_ON_BOARD_DI, "baseline_slot": CAP_BASELINE_SLOT,
                   "chunk_retransmit": CAP_CHUNK_RETRANSMIT}
_NEVER_BUSY = (MsgType.INFO, MsgType.STATUS)  # answered even while an acquisition runs
_REQUEST_TYPES = frozenset(range(MsgType.INFO, MsgType.READ_DI + 1))


class NodeSetupError(ValueError):
    """A scenario the node cannot represent on the wire (too many channels, long node id)."""


class _Refused(Exception):
    """Internal: answer the current request with an ERROR reply."""

    def __init__(self, code: ErrorCode, detail: str) -> None:
        super().__init__(detail)
        self.code = code
        self.detail = detail


@dataclass(frozen=True)
class _Stored:
    measurement_id: int
    is_baseline: bool
    channel_mask: int
    settings: ConfigureReply  # what it was taken with
    acquisition: physics.Acquisition
    measurement: Measurement  # all enabled channels, full rate


@dataclass(frozen=True)
class _StoredDi:
    reply: ComputeDiReply
    grid: Grid
    pixels: np.ndarray  # float32 [n_axial, n_angle]


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
        self._next_measurement_id = 1
        self._next_di_id = 1
        self._measurements: OrderedDict[int, _Stored] = OrderedDict()
        self._baseline_id = 0
        self._di_maps: OrderedDict[int, _StoredDi] = OrderedDict()
        self._cache: OrderedDict[int, tuple[int, int, bytes, list[Frame]]] = OrderedDict()
        self._busy_until = 0.0
        self._running: tuple[int, int, int, bytes] | None = None  # the acquisition in progress
        self._stuck_busy = False
        self.rejected_requests = 0
        self.last_service_s = 0.0
        self.config = self.power_up_settings()

    def power_up_settings(self) -> ConfigureReply:
        """The settings in force after a boot: the scenario's ``power_up`` keys, else its own."""
        scn, up = self.scenario, self.scenario.power_up
        return ConfigureReply(
            float(np.float32(up.excitation_hz or scn.excitation.frequency_hz)), up.cycles or scn.excitation.cycles,
            up.averaging or scn.acquisition.averaging, (1 << len(scn.rings.rx_angles)) - 1,
            up.n_samples or scn.acquisition.n_samples,
        )

    @property
    def busy(self) -> bool:
        return self._stuck_busy or self.clock() < self._busy_until

    def stored_codes(self, measurement_id: int) -> np.ndarray | None:
        """A copy of a stored measurement's codes [n_enabled_channels, n] (an oracle for tests)."""
        stored = self._measurements.get(measurement_id)
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
        cached = self._cache.get(request.request_id)
        if cached is not None and cached[:3] == (version, request.msg_type, request.payload) and not (
            request.msg_type == MsgType.ACQUIRE and Violation.ACQUIRES_TWICE in self.violations
        ):
            return [self._replay(f) for f in cached[3]]
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
        except _Refused as refused:
            frames = self._error(request, refused.code, refused.detail, version)
        except (physics.PhysicsError, MeasurementError, GridError) as exc:
            # The simulated hardware failed: answer like firmware would, keep serving.
            frames = self._error(request, ErrorCode.HARDWARE_FAULT, f"{type(exc).__name__}: {exc}", version)
        refused_now = frames[0].msg_type == MsgType.ERROR
        if isinstance(message, (ConfigureRequest, AcquireRequest, ComputeDiRequest)) and (
            not refused_now or Violation.CACHES_ERRORS in self.violations
        ):
            self._cache[request.request_id] = (version, request.msg_type, request.payload, frames)
            self._cache.move_to_end(request.request_id)
            while len(self._cache) > REPLY_CACHE_SIZE:
                self._cache.popitem(last=False)
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
            float(scn.acquisition.fs_hz), self._max_samples(), float(scn.rings.tx_rx_distance_mm),
            float(scn.pipe.outer_circumference_mm), float(scn.pipe.velocity_m_s), len(tx), len(rx), tx, rx,
            self.version_min, min(self.version_max, 255),
        )]

    def _info_request(self, message: InfoRequest) -> list[Message]:
        return self._info(self.version_max)  # a version-1 node: INFO in its own version

    def _max_samples(self) -> int:
        """The longest record CONFIGURE accepts: the firmware's limit; a replayed record, no longer than it was simulated."""
        if self._recorded is not None:
            return min(self.scenario.max_samples, self._recorded.n_samples)
        return self.scenario.max_samples

    def _status(self, message: StatusRequest) -> list[Message]:
        last = next(reversed(self._measurements.values()), None)
        idle = self._recorded.baseline.temperature_c if self._recorded else self.scenario.temperature.mean_c
        temperature = last.acquisition.temperature_c if last else idle
        return [StatusReply(
            int(self.clock() - self._boot_time), self.boot_id, float(temperature), SUPPLY_V,
            self.crc_errors, self.framing_errors, self.rejected_requests, self._baseline_id,
            len(self._measurements), int(self.busy),
        )]

    def _configure(self, message: ConfigureRequest) -> list[Message]:
        n_rx = len(self.scenario.rings.rx_angles)
        if not (1e3 <= message.excitation_hz <= 1e6 and math.isfinite(message.excitation_hz)):
            raise _Refused(ErrorCode.BAD_ARGUMENT, "excitation_hz outside 1 kHz..1 MHz")
        if not 1 <= message.cycles <= 50:
            raise _Refused(ErrorCode.BAD_ARGUMENT, "cycles outside 1..50")
        averaging, n_samples, max_samples = message.averaging, message.n_samples, self._max_samples()
        if Violation.CLAMPS_SETTINGS in self.violations:
            averaging, n_samples = min(averaging, 10000), min(n_samples, max_samples)
        if not 1 <= averaging <= 10000:
            raise _Refused(ErrorCode.BAD_ARGUMENT, "averaging outside 1..10000")
        if message.channel_mask == 0 or message.channel_mask >> n_rx:
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"channel_mask must select channels of 0..{n_rx - 1}")
        if not 2 <= n_samples <= max_samples:
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"n_samples outside 2..{max_samples}")
        recorded = self._recorded.baseline if self._recorded is not None else None
        if recorded is not None and not (math.isclose(message.excitation_hz, recorded.excitation_hz, rel_tol=1e-6)
                                         and message.cycles == recorded.cycles):
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"this node replays full-wave records of {recorded.excitation_hz:g} Hz, "
                                                   f"{recorded.cycles} cycles only")
        self.config = ConfigureReply(float(np.float32(message.excitation_hz)), message.cycles, averaging,
                                     message.channel_mask, n_samples)
        return [self.config]

    def _configured_scenario(self) -> NodeScenario:
        scn, cfg = self.scenario, self.config
        return scn.model_copy(update={
            "excitation": scn.excitation.model_copy(update={"frequency_hz": cfg.excitation_hz, "cycles": cfg.cycles}),
            "acquisition": scn.acquisition.model_copy(update={"averaging": cfg.averaging, "n_samples": cfg.n_samples}),
        })

    def _acquire(self, message: AcquireRequest) -> list[Message]:
        if message.as_baseline and not self.capabilities & CAP_BASELINE_SLOT:
            raise _Refused(ErrorCode.BAD_ARGUMENT, "no baseline slot (capability BASELINE_SLOT absent)")
        scn = self._configured_scenario()
        elapsed_s = self.clock() - self._epoch
        if self._recorded is not None:
            acquisition = acquire_recorded(scn, self._recorded, elapsed_s, self._rng)
        else:
            acquisition = physics.acquire(scn, elapsed_s, self._rng)
        rows = [i for i in range(len(scn.rings.rx_angles)) if self.config.channel_mask >> i & 1]
        full = acquisition.to_measurement(scn)
        if full.n_rx != len(rows):  # keep only the enabled receivers, as the FPGA does
            full = dataclasses.replace(full, traces=full.traces[rows], rx_angles_deg=full.rx_angles_deg[rows])
            acquisition = dataclasses.replace(acquisition, codes=np.ascontiguousarray(acquisition.codes[rows]))
        measurement_id = self._next_measurement_id
        self._next_measurement_id += 1
        stored = _Stored(measurement_id, bool(message.as_baseline), self.config.channel_mask, self.config,
                         acquisition, full)
        if message.as_baseline:
            self._measurements.pop(self._baseline_id, None)
            self._baseline_id = measurement_id
        self._measurements[measurement_id] = stored
        while len(self._measurements) > MAX_MEASUREMENTS:  # evict the oldest, never the baseline
            oldest = next(k for k in self._measurements if k != self._baseline_id)
            del self._measurements[oldest]
        self.last_service_s = self.config.averaging * SHOT_PERIOD_S
        cfg = self.config
        return [AcquireReply(measurement_id, int(stored.is_baseline), float(acquisition.temperature_c),
                             cfg.channel_mask, cfg.n_samples, int(self.clock() - self._boot_time), self.boot_id,
                             cfg.excitation_hz, cfg.cycles, cfg.averaging, float(acquisition.fs_hz))]

    def _stored(self, measurement_id: int) -> _Stored:
        stored = self._measurements.get(measurement_id)
        if stored is None:
            raise _Refused(ErrorCode.NO_SUCH_MEASUREMENT, f"measurement {measurement_id} is not in RAM")
        return stored

    def _read_traces(self, message: ReadTracesRequest) -> list[Message]:
        stored = self._stored(message.measurement_id)
        n = stored.acquisition.codes.shape[1]
        if message.channel_mask == 0 or message.channel_mask & ~stored.channel_mask:
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"channel_mask 0x{message.channel_mask:X} not in 0x{stored.channel_mask:X}")
        count = message.count or n - message.start
        if message.start >= n or count < 1 or message.start + count > n:
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"samples {message.start}+{count} outside 0..{n}")
        stored_channels = [i for i in range(MAX_CHANNELS) if stored.channel_mask >> i & 1]
        rows = [stored_channels.index(i) for i in stored_channels if message.channel_mask >> i & 1]
        codes = stored.acquisition.codes[rows, message.start : message.start + count]
        data = np.ascontiguousarray(codes, dtype="<i2").tobytes()
        meta = TraceMeta(
            self.boot_id, stored.measurement_id, int(stored.is_baseline), message.channel_mask, message.start,
            count, float(stored.acquisition.fs_hz), float(stored.acquisition.t0_s),
            float(stored.acquisition.volts_per_code), float(stored.acquisition.temperature_c),
            self.scenario.acquisition.adc_bits, len(data), CHUNK_BYTES, n_chunks_for(len(data), CHUNK_BYTES),
            crc32c(data), stored.settings.excitation_hz, stored.settings.cycles, stored.settings.averaging,
            stored.channel_mask, n,
        )
        return [meta, *self._chunks(data, message.chunks)]

    def _chunks(self, data: bytes, wanted: tuple[int, ...]) -> list[BulkChunk]:
        pieces = split_chunks(data, CHUNK_BYTES)
        if wanted and not self.capabilities & CAP_CHUNK_RETRANSMIT:
            raise _Refused(ErrorCode.BAD_ARGUMENT, "no chunk lists (capability CHUNK_RETRANSMIT absent)")
        if Violation.IGNORES_CHUNK_LIST in self.violations:
            wanted = ()
        indices = sorted(set(wanted)) if wanted else range(len(pieces))
        if any(i >= len(pieces) for i in indices):
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"chunk index beyond {len(pieces)} chunks")
        stated = len(pieces) + (Violation.MISSTATES_CHUNK_COUNT in self.violations)
        return [BulkChunk(i, stated, pieces[i]) for i in indices]

    def _decimated(self, stored: _Stored, factor: int) -> Measurement:
        method: Decimation = "boxcar" if Violation.DI_BOXCAR_DECIMATION in self.violations else "subsample"
        return decimated(stored.measurement, stored.acquisition.codes, stored.acquisition.volts_per_code, factor,
                         method)

    def _compute_di(self, message: ComputeDiRequest) -> list[Message]:
        baseline_id = message.baseline_id or self._baseline_id
        if baseline_id == 0:
            raise _Refused(ErrorCode.NO_BASELINE, "no baseline stored")
        baseline, current = self._stored(baseline_id), self._stored(message.current_id)
        factor = message.decimation or self.scenario.acquisition.decimation
        if not 1 <= factor <= 100:
            raise _Refused(ErrorCode.BAD_ARGUMENT, "decimation outside 1..100")
        try:
            grid = requested_grid(message, self.scenario.rings.tx_rx_distance_mm)
            pixels, peak = onboard_map(self._decimated(baseline, factor), self._decimated(current, factor), grid)
        except GridRefused as exc:
            raise _Refused(ErrorCode.BAD_ARGUMENT, str(exc)) from exc
        except BaselineMismatch as exc:
            raise _Refused(ErrorCode.BAD_ARGUMENT, f"baseline mismatch: {exc}") from exc
        reply = ComputeDiReply(
            self._next_di_id, current.measurement_id, baseline.measurement_id, factor, grid.axial_count,
            grid.angle_count, float(pixels[peak]), float(grid.axial_mm[peak[0]]), float(grid.angle_deg[peak[1]]),
        )
        self._next_di_id += 1
        self._di_maps[reply.di_id] = _StoredDi(reply, grid, pixels)
        while len(self._di_maps) > MAX_DI_MAPS:
            self._di_maps.popitem(last=False)
        return [reply]

    def _read_di(self, message: ReadDiRequest) -> list[Message]:
        stored = self._di_maps.get(message.di_id)
        if stored is None:
            raise _Refused(ErrorCode.NO_SUCH_DI, f"DI map {message.di_id} is not in RAM")
        data = np.ascontiguousarray(stored.pixels, dtype="<f4").tobytes()
        r, g = stored.reply, stored.grid
        meta = DiMeta(
            self.boot_id, r.di_id, r.current_id, r.baseline_id, r.decimation, g.axial_count, g.angle_count,
            g.axial_start_mm, g.axial_step_mm, g.angle_start_deg, g.angle_step_deg, len(data), CHUNK_BYTES,
            n_chunks_for(len(data), CHUNK_BYTES), crc32c(data),
        )
        return [meta, *self._chunks(data, message.chunks)]

    _HANDLERS: ClassVar[dict[type, Callable]] = {
        InfoRequest: _info_request,
        StatusRequest: _status,
        ConfigureRequest: _configure,
        AcquireRequest: _acquire,
        ReadTracesRequest: _read_traces,
        ComputeDiRequest: _compute_di,
        ReadDiRequest: _read_di,
    }
