"""The mock node's bulk replies (pure): READ_TRACES and READ_DI as a *_META frame and the chunks
of the transfer, its CRC-32C over the whole; a chunk list (only some chunks, again) is honoured
by a node with CHUNK_RETRANSMIT and refused by one without."""
from __future__ import annotations

import numpy as np

from mocknode.faults import Violation
from mocknode.node_ram import MAX_CHANNELS, StoredDi, StoredMeasurement
from mocknode.refusal import Refused
from protocol.bulk import n_chunks_for, split_chunks
from protocol.crc import crc32c
from protocol.messages import BulkChunk, DiMeta, ErrorCode, Message, ReadDiRequest, ReadTracesRequest, TraceMeta

CHUNK_BYTES = 2048  # bulk payload per frame: 98 % wire efficiency, 4 KiB frame buffers


def trace_reply(message: ReadTracesRequest, stored: StoredMeasurement, boot_id: int, adc_bits: int,
                chunk_retransmit: bool, violations: frozenset[Violation]) -> list[Message]:
    """TRACE_META and the chunks of the codes READ_TRACES asks for; BAD_ARGUMENT for channels or
    samples the measurement does not have."""
    n = stored.acquisition.codes.shape[1]
    if message.channel_mask == 0 or message.channel_mask & ~stored.channel_mask:
        raise Refused(ErrorCode.BAD_ARGUMENT,
                      f"channel_mask 0x{message.channel_mask:X} not in 0x{stored.channel_mask:X}")
    count = message.count or n - message.start
    if message.start >= n or count < 1 or message.start + count > n:
        raise Refused(ErrorCode.BAD_ARGUMENT, f"samples {message.start}+{count} outside 0..{n}")
    stored_channels = [i for i in range(MAX_CHANNELS) if stored.channel_mask >> i & 1]
    rows = [stored_channels.index(i) for i in stored_channels if message.channel_mask >> i & 1]
    codes = stored.acquisition.codes[rows, message.start : message.start + count]
    data = np.ascontiguousarray(codes, dtype="<i2").tobytes()
    meta = TraceMeta(
        boot_id, stored.measurement_id, int(stored.is_baseline), message.channel_mask, message.start,
        count, float(stored.acquisition.fs_hz), float(stored.acquisition.t0_s),
        float(stored.acquisition.volts_per_code), float(stored.acquisition.temperature_c),
        adc_bits, len(data), CHUNK_BYTES, n_chunks_for(len(data), CHUNK_BYTES),
        crc32c(data), stored.settings.excitation_hz, stored.settings.cycles, stored.settings.averaging,
        stored.channel_mask, n,
    )
    return [meta, *chunks(data, message.chunks, chunk_retransmit, violations)]


def di_reply(message: ReadDiRequest, stored: StoredDi, boot_id: int, chunk_retransmit: bool,
             violations: frozenset[Violation]) -> list[Message]:
    """DI_META and the chunks of a stored DI map's float32 pixels."""
    data = np.ascontiguousarray(stored.pixels, dtype="<f4").tobytes()
    r, g = stored.reply, stored.grid
    meta = DiMeta(
        boot_id, r.di_id, r.current_id, r.baseline_id, r.decimation, g.axial_count, g.angle_count,
        g.axial_start_mm, g.axial_step_mm, g.angle_start_deg, g.angle_step_deg, len(data), CHUNK_BYTES,
        n_chunks_for(len(data), CHUNK_BYTES), crc32c(data),
    )
    return [meta, *chunks(data, message.chunks, chunk_retransmit, violations)]


def chunks(data: bytes, wanted: tuple[int, ...], chunk_retransmit: bool,
           violations: frozenset[Violation]) -> list[BulkChunk]:
    """The chunks of ``data`` in ``wanted`` (all of them for ())."""
    pieces = split_chunks(data, CHUNK_BYTES)
    if wanted and not chunk_retransmit:
        raise Refused(ErrorCode.BAD_ARGUMENT, "no chunk lists (capability CHUNK_RETRANSMIT absent)")
    if Violation.IGNORES_CHUNK_LIST in violations:
        wanted = ()
    indices = sorted(set(wanted)) if wanted else range(len(pieces))
    if any(i >= len(pieces) for i in indices):
        raise Refused(ErrorCode.BAD_ARGUMENT, f"chunk index beyond {len(pieces)} chunks")
    stated = len(pieces) + (Violation.MISSTATES_CHUNK_COUNT in violations)
    return [BulkChunk(i, stated, pieces[i]) for i in indices]
