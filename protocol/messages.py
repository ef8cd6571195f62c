"""Typed messages: one frozen dataclass per message type, packed little-endian with ``struct``.

Messages know fields only. Requests have types 0x01-0x0F, their replies ``type | 0x80``;
bulk data travels in :class:`BulkChunk` frames (0x90); any request may be answered by
:class:`ErrorReply` (0xFF). See docs/protocol.md for the field tables.

Layouts are versioned: version 2 appends fields to three version-1 messages (INFO_REPLY,
ACQUIRE_REPLY, TRACE_META) and changes nothing else, so ``encode(version)`` and
``decode(payload, version)`` differ only in those tails. Fields a version-1 payload does not
carry decode as None.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import re
import struct
from dataclasses import dataclass
from typing import Any, ClassVar, Self

from protocol.versions import PROTOCOL_VERSION

NODE_ID_BYTES = 32
MAX_ERROR_DETAIL_BYTES = 64
MAX_CHUNK_LIST = 512  # chunk indices one READ_* request may name
MAX_DI_PIXELS = 65536  # the largest on-board DI map a COMPUTE_DI may ask for (float32: 256 KB)


class MessageError(ValueError):
    """A payload does not match its message type (length, counts, field values)."""


class UnknownMessageType(MessageError):
    """The frame's message type is not part of this protocol version."""


class ErrorCode(enum.IntEnum):
    """Codes of ERROR replies (docs/protocol.md, "Error replies")."""

    BAD_VERSION = 1
    UNKNOWN_COMMAND = 2
    MALFORMED = 3
    BAD_ARGUMENT = 4
    NO_SUCH_MEASUREMENT = 5
    NO_BASELINE = 6
    BUSY = 7
    NO_SUCH_DI = 8
    HARDWARE_FAULT = 9


class MsgType(enum.IntEnum):
    INFO = 0x01
    STATUS = 0x02
    CONFIGURE = 0x03
    ACQUIRE = 0x04
    READ_TRACES = 0x05
    COMPUTE_DI = 0x06
    READ_DI = 0x07
    INFO_REPLY = 0x81
    STATUS_REPLY = 0x82
    CONFIGURE_REPLY = 0x83
    ACQUIRE_REPLY = 0x84
    TRACE_META = 0x85
    COMPUTE_DI_REPLY = 0x86
    DI_META = 0x87
    BULK_CHUNK = 0x90
    ERROR = 0xFF


CAP_ON_BOARD_DI = 0x01
CAP_BASELINE_SLOT = 0x02
CAP_CHUNK_RETRANSMIT = 0x04


CAPABILITY_NAMES = {CAP_ON_BOARD_DI: "ON_BOARD_DI", CAP_BASELINE_SLOT: "BASELINE_SLOT",
                    CAP_CHUNK_RETRANSMIT: "CHUNK_RETRANSMIT"}
ALL_CAPABILITIES = CAP_ON_BOARD_DI | CAP_BASELINE_SLOT | CAP_CHUNK_RETRANSMIT

_FORMAT_TOKEN = re.compile(r"\d*[a-zA-Z?]")


@functools.cache
def _leading_fields(fmt: str, n_fields: int) -> struct.Struct:
    """The struct of the first ``n_fields`` fields of little-endian format ``fmt``."""
    return struct.Struct("<" + "".join(_FORMAT_TOKEN.findall(fmt.lstrip("<"))[:n_fields]))


@dataclass(frozen=True)
class Message:
    """Base: fixed fields packed with ``_STRUCT`` in declaration order, plus an optional tail.

    ``V1_FIELDS``: how many leading fixed fields the version-1 layout has (None: every version
    has them all); the others were appended in version 2 and are None in a version-1 message.
    """

    TYPE: ClassVar[int]
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<")
    V1_FIELDS: ClassVar[int | None] = None

    @classmethod
    def layout(cls, version: int = PROTOCOL_VERSION) -> struct.Struct:
        """The fixed part of this message in ``version``."""
        if cls.V1_FIELDS is None or version >= 2:
            return cls._STRUCT
        return _leading_fields(cls._STRUCT.format, cls.V1_FIELDS)

    def _fixed(self) -> tuple:
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))

    def _tail(self, version: int) -> bytes:
        return b""

    def encode(self, version: int = PROTOCOL_VERSION) -> bytes:
        """Payload bytes in ``version``; raises :class:`MessageError` if a field does not fit its wire type."""
        layout = self.layout(version)
        fixed = self._fixed()[: len(_FORMAT_TOKEN.findall(layout.format.lstrip("<")))]
        try:
            return layout.pack(*fixed) + self._tail(version)
        except struct.error as exc:
            raise MessageError(f"{type(self).__name__} (version {version}): {exc}") from exc

    @classmethod
    def decode(cls, payload: bytes, version: int = PROTOCOL_VERSION) -> Self:
        layout = cls.layout(version)
        _check_tail_len(cls, payload, layout.size)
        return cls(*layout.unpack(payload))


def _check_tail_len(cls: type, payload: bytes, need: int) -> None:
    if len(payload) != need:
        raise MessageError(f"{cls.__name__} payload is {len(payload)} bytes, expected {need}")


def _pack_chunk_list(chunks: tuple[int, ...]) -> bytes:
    if len(chunks) > MAX_CHUNK_LIST:
        raise MessageError(f"{len(chunks)} chunk indices exceed {MAX_CHUNK_LIST}")
    try:
        return struct.pack(f"<H{len(chunks)}H", len(chunks), *chunks)
    except struct.error as exc:
        raise MessageError(f"chunk list: {exc}") from exc


def _unpack_chunk_list(cls: type, payload: bytes, offset: int) -> tuple[int, ...]:
    if len(payload) < offset + 2:
        raise MessageError(f"{cls.__name__} payload is {len(payload)} bytes, too short")
    (n,) = struct.unpack_from("<H", payload, offset)
    if n > MAX_CHUNK_LIST:
        raise MessageError(f"{cls.__name__} names {n} chunks, more than {MAX_CHUNK_LIST}")
    _check_tail_len(cls, payload, offset + 2 + 2 * n)
    return struct.unpack_from(f"<{n}H", payload, offset + 2)


class _ChunkListRequest(Message):
    """A bulk read request: fixed fields, then the list of chunks to (re)send (empty = all).

    Subclasses declare their fixed fields and ``chunks`` last; ``_STRUCT`` covers the fixed ones.
    """

    chunks: tuple[int, ...]

    def _fixed(self) -> tuple:
        return super()._fixed()[:-1]

    def _tail(self, version: int) -> bytes:
        return _pack_chunk_list(tuple(self.chunks))

    @classmethod
    def decode(cls, payload: bytes, version: int = PROTOCOL_VERSION):
        chunks = _unpack_chunk_list(cls, payload, cls._STRUCT.size)
        fields: tuple[Any, ...] = (*cls._STRUCT.unpack_from(payload), chunks)
        return cls(*fields)


# ---------------------------------------------------------------- INFO (capability exchange)
@dataclass(frozen=True)
class InfoRequest(Message):
    """HELLO: the host's supported protocol versions; the node answers with INFO_REPLY."""

    TYPE: ClassVar[int] = MsgType.INFO
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BB")
    host_version_min: int = 1
    host_version_max: int = 1


@dataclass(frozen=True)
class InfoReply(Message):
    """Identity, capabilities, acquisition limits and ring geometry of the node.

    Version 2 appends the range of versions the node speaks after the angle lists. The first
    36 bytes (node_id, firmware, protocol_version) keep their offsets in every version, so a
    host can name the version of a node it cannot otherwise parse (:meth:`announced_version`).
    """

    TYPE: ClassVar[int] = MsgType.INFO_REPLY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct(f"<{NODE_ID_BYTES}sBBBBIIHHBBBBfIfffBB")
    _V2_TAIL: ClassVar[struct.Struct] = struct.Struct("<BB")
    PROTOCOL_VERSION_OFFSET: ClassVar[int] = NODE_ID_BYTES + 3
    node_id: str
    fw_major: int
    fw_minor: int
    fw_patch: int
    protocol_version: int
    capabilities: int
    boot_id: int
    max_frame_bytes: int
    chunk_bytes: int
    n_channels: int
    adc_bits: int
    decimation: int
    max_measurements: int
    fs_hz: float
    max_samples: int
    tx_rx_distance_mm: float
    circumference_mm: float
    velocity_m_s: float
    n_tx: int
    n_rx: int
    tx_angles_deg: tuple[float, ...] = ()
    rx_angles_deg: tuple[float, ...] = ()
    version_min: int | None = None  # version 2: the versions the node speaks
    version_max: int | None = None

    @property
    def firmware_version(self) -> str:
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_patch}"

    def has(self, capability: int) -> bool:
        return bool(self.capabilities & capability)

    def _fixed(self) -> tuple:
        raw = self.node_id.encode("utf-8")
        if len(raw) > NODE_ID_BYTES:
            raise MessageError(f"node_id {self.node_id!r} is longer than {NODE_ID_BYTES} bytes")
        if len(self.tx_angles_deg) != self.n_tx or len(self.rx_angles_deg) != self.n_rx:
            raise MessageError("n_tx/n_rx do not match the angle lists")
        return (raw,) + super()._fixed()[1:-4]

    def _tail(self, version: int) -> bytes:
        angles = tuple(self.tx_angles_deg) + tuple(self.rx_angles_deg)
        tail = struct.pack(f"<{len(angles)}f", *angles)
        if version >= 2:
            try:
                tail += self._V2_TAIL.pack(self.version_min, self.version_max)
            except struct.error as exc:
                raise MessageError(f"InfoReply version range: {exc}") from exc
        return tail

    @classmethod
    def announced_version(cls, payload: bytes) -> int:
        """The ``protocol_version`` of an INFO_REPLY of any version (its offset never changes)."""
        if len(payload) <= cls.PROTOCOL_VERSION_OFFSET:
            raise MessageError(f"InfoReply payload is {len(payload)} bytes, too short for its version")
        return payload[cls.PROTOCOL_VERSION_OFFSET]

    @classmethod
    def decode(cls, payload: bytes, version: int = PROTOCOL_VERSION) -> InfoReply:
        size = cls._STRUCT.size
        if len(payload) < size:
            raise MessageError(f"InfoReply payload is {len(payload)} bytes, shorter than {size}")
        fixed = cls._STRUCT.unpack_from(payload)
        n_tx, n_rx = fixed[-2], fixed[-1]
        angles_end = size + 4 * (n_tx + n_rx)
        _check_tail_len(cls, payload, angles_end + (cls._V2_TAIL.size if version >= 2 else 0))
        angles = struct.unpack_from(f"<{n_tx + n_rx}f", payload, size)
        versions = cls._V2_TAIL.unpack_from(payload, angles_end) if version >= 2 else (None, None)
        try:
            node_id = fixed[0].rstrip(b"\x00").decode("utf-8")
        except UnicodeDecodeError as exc:
            raise MessageError(f"node_id is not UTF-8: {exc}") from exc
        # the angle lists and the version range come after the fixed fields
        fields: tuple[Any, ...] = (node_id, *fixed[1:], angles[:n_tx], angles[n_tx:], *versions)
        return cls(*fields)


# ---------------------------------------------------------------- STATUS
@dataclass(frozen=True)
class StatusRequest(Message):
    TYPE: ClassVar[int] = MsgType.STATUS


@dataclass(frozen=True)
class StatusReply(Message):
    """Health counters; ``baseline_id`` is 0 when no baseline is stored."""

    TYPE: ClassVar[int] = MsgType.STATUS_REPLY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIffIIIIBB")
    uptime_s: int
    boot_id: int
    temperature_c: float
    supply_v: float
    crc_errors: int
    framing_errors: int
    rejected_requests: int
    baseline_id: int
    n_measurements: int
    busy: int

    @property
    def baseline_stored(self) -> bool:
        return self.baseline_id != 0


# ---------------------------------------------------------------- CONFIGURE
@dataclass(frozen=True)
class ConfigureRequest(Message):
    """Excitation and acquisition settings; bit i of ``channel_mask`` enables Rx channel i."""

    TYPE: ClassVar[int] = MsgType.CONFIGURE
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<fBHII")
    excitation_hz: float
    cycles: int
    averaging: int
    channel_mask: int
    n_samples: int


@dataclass(frozen=True)
class ConfigureReply(ConfigureRequest):
    """The settings now in force (the node echoes what it applied)."""

    TYPE: ClassVar[int] = MsgType.CONFIGURE_REPLY


# ---------------------------------------------------------------- ACQUIRE
@dataclass(frozen=True)
class AcquireRequest(Message):
    TYPE: ClassVar[int] = MsgType.ACQUIRE
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")
    as_baseline: int = 0


@dataclass(frozen=True)
class AcquireReply(Message):
    """The new measurement; version 2 adds the settings it was actually taken with."""

    TYPE: ClassVar[int] = MsgType.ACQUIRE_REPLY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IBfIIIIfBHf")
    V1_FIELDS: ClassVar[int | None] = 7
    measurement_id: int
    is_baseline: int
    temperature_c: float
    channel_mask: int
    n_samples: int
    uptime_s: int
    boot_id: int
    excitation_hz: float | None = None  # version 2 from here
    cycles: int | None = None
    averaging: int | None = None
    fs_hz: float | None = None


# ---------------------------------------------------------------- READ_TRACES
@dataclass(frozen=True)
class ReadTracesRequest(_ChunkListRequest):
    """Raw int16 codes of one measurement; ``count`` 0 means "to the end"; no chunks = all."""

    TYPE: ClassVar[int] = MsgType.READ_TRACES
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIII")
    measurement_id: int
    channel_mask: int
    start: int
    count: int
    chunks: tuple[int, ...] = ()


@dataclass(frozen=True)
class TraceMeta(Message):
    """First frame of a READ_TRACES reply: what the chunks will hold and their CRC-32C.

    Version 2 adds what the measurement was taken with: excitation, averaging, and the whole
    record's channel mask and length (``channel_mask``/``count`` describe only this read).
    """

    TYPE: ClassVar[int] = MsgType.TRACE_META
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIBIIIffffBIHHIfBHII")
    V1_FIELDS: ClassVar[int | None] = 15
    boot_id: int
    measurement_id: int
    is_baseline: int
    channel_mask: int
    start: int
    count: int
    fs_hz: float
    t0_s: float
    volts_per_code: float
    temperature_c: float
    adc_bits: int
    total_bytes: int
    chunk_bytes: int
    n_chunks: int
    transfer_crc32c: int
    excitation_hz: float | None = None  # version 2 from here
    cycles: int | None = None
    averaging: int | None = None
    record_channel_mask: int | None = None
    record_n_samples: int | None = None


# ---------------------------------------------------------------- COMPUTE_DI / READ_DI
@dataclass(frozen=True)
class ComputeDiRequest(Message):
    """DI map of ``current_id`` against ``baseline_id`` (0 = the stored baseline)."""

    TYPE: ClassVar[int] = MsgType.COMPUTE_DI
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIBffHffH")
    current_id: int
    baseline_id: int = 0
    decimation: int = 0  # 0 = the node's default
    axial_start_mm: float = 0.0
    axial_step_mm: float = 0.0
    axial_count: int = 0  # 0 = the node's default grid (the other grid fields are ignored)
    angle_start_deg: float = 0.0
    angle_step_deg: float = 0.0
    angle_count: int = 0


@dataclass(frozen=True)
class ComputeDiReply(Message):
    TYPE: ClassVar[int] = MsgType.COMPUTE_DI_REPLY
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIIBHHfff")
    di_id: int
    current_id: int
    baseline_id: int
    decimation: int
    n_axial: int
    n_angle: int
    peak_value: float
    peak_axial_mm: float
    peak_angle_deg: float


@dataclass(frozen=True)
class ReadDiRequest(_ChunkListRequest):
    TYPE: ClassVar[int] = MsgType.READ_DI
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<I")
    di_id: int
    chunks: tuple[int, ...] = ()


@dataclass(frozen=True)
class DiMeta(Message):
    """First frame of a READ_DI reply: uniform grid spec; pixels float32 [n_axial, n_angle]."""

    TYPE: ClassVar[int] = MsgType.DI_META
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIIIBHHffffIHHI")
    boot_id: int
    di_id: int
    current_id: int
    baseline_id: int
    decimation: int
    n_axial: int
    n_angle: int
    axial_start_mm: float
    axial_step_mm: float
    angle_start_deg: float
    angle_step_deg: float
    total_bytes: int
    chunk_bytes: int
    n_chunks: int
    transfer_crc32c: int


# ---------------------------------------------------------------- bulk data and errors
@dataclass(frozen=True)
class BulkChunk(Message):
    """Chunk ``index`` of ``n_chunks`` of the bulk data announced by the preceding *_META."""

    TYPE: ClassVar[int] = MsgType.BULK_CHUNK
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HH")
    index: int
    n_chunks: int
    data: bytes = b""

    def _fixed(self) -> tuple:
        return (self.index, self.n_chunks)

    def _tail(self, version: int) -> bytes:
        return bytes(self.data)

    @classmethod
    def decode(cls, payload: bytes, version: int = PROTOCOL_VERSION) -> BulkChunk:
        if len(payload) < cls._STRUCT.size:
            raise MessageError(f"BulkChunk payload is {len(payload)} bytes, too short")
        index, n_chunks = cls._STRUCT.unpack_from(payload)
        if index >= n_chunks:
            raise MessageError(f"chunk index {index} is not below n_chunks={n_chunks}")
        return cls(index, n_chunks, bytes(payload[cls._STRUCT.size :]))


@dataclass(frozen=True)
class ErrorReply(Message):
    """The request could not be carried out; ``detail`` is short ASCII for logs."""

    TYPE: ClassVar[int] = MsgType.ERROR
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HBB")
    code: int
    request_type: int
    detail: str = ""

    def _fixed(self) -> tuple:
        return (self.code, self.request_type, 0)

    def _tail(self, version: int) -> bytes:
        return self.detail.encode("ascii", "replace")[:MAX_ERROR_DETAIL_BYTES]

    @classmethod
    def decode(cls, payload: bytes, version: int = PROTOCOL_VERSION) -> ErrorReply:
        size = cls._STRUCT.size
        if not size <= len(payload) <= size + MAX_ERROR_DETAIL_BYTES:
            raise MessageError(f"ErrorReply payload is {len(payload)} bytes")
        code, request_type, _ = cls._STRUCT.unpack_from(payload)
        return cls(code, request_type, payload[size:].decode("ascii", "replace"))


MESSAGE_CLASSES: dict[int, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        InfoRequest, InfoReply, StatusRequest, StatusReply, ConfigureRequest, ConfigureReply,
        AcquireRequest, AcquireReply, ReadTracesRequest, TraceMeta, ComputeDiRequest,
        ComputeDiReply, ReadDiRequest, DiMeta, BulkChunk, ErrorReply,
    )
}


def decode_message(msg_type: int, payload: bytes, version: int = PROTOCOL_VERSION) -> Message:
    """Decode a payload by its frame's message type, in the layout of ``version`` (the frame
    header's); raises :class:`MessageError`."""
    cls = MESSAGE_CLASSES.get(msg_type)
    if cls is None:
        raise UnknownMessageType(f"unknown message type 0x{msg_type:02X}")
    return cls.decode(bytes(payload), version)
