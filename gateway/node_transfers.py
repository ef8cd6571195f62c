"""What the gateway's node client returns from a bulk read, built from the read's META reply and
its reassembled, CRC-32C-verified bytes (pure); and the channel masks of requests and replies."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gateway.node_errors import TransferError
from imaging.grid import Grid
from protocol.messages import DiMeta, TraceMeta


@dataclass(frozen=True)
class TraceTransfer:
    """Raw ADC codes of one measurement, verified end to end."""

    measurement_id: int
    boot_id: int
    is_baseline: bool
    channels: tuple[int, ...]
    start: int
    codes: np.ndarray  # int16 [n_channels, n_samples]
    volts_per_code: float
    fs_hz: float
    t0_s: float
    temperature_c: float
    adc_bits: int
    transfer_crc32c: int
    chunks_rerequested: int
    # What the record was taken with, as the node states it (protocol version 2; None from version 1).
    excitation_hz: float | None = None
    cycles: int | None = None
    averaging: int | None = None
    record_channels: tuple[int, ...] | None = None
    record_n_samples: int | None = None

    @property
    def volts(self) -> np.ndarray:
        return self.codes.astype(np.float64) * self.volts_per_code


@dataclass(frozen=True)
class DiTransfer:
    """An on-board DI map, verified end to end."""

    di_id: int
    boot_id: int
    current_id: int
    baseline_id: int
    decimation: int
    grid: Grid
    pixels: np.ndarray  # float32 [n_axial, n_angle]
    transfer_crc32c: int
    chunks_rerequested: int


def mask_of(channels: tuple[int, ...] | list[int] | None, n_channels: int) -> int:
    """The 32-bit channel mask of ``channels`` (None: all ``n_channels``)."""
    chosen = range(n_channels) if channels is None else channels
    mask = 0
    for ch in chosen:
        if not 0 <= ch < 32:
            raise ValueError(f"channel {ch} is outside 0..31")
        mask |= 1 << ch
    return mask


def channels_of(mask: int) -> tuple[int, ...]:
    """The channels a 32-bit channel mask selects, in order."""
    return tuple(i for i in range(32) if mask >> i & 1)


def trace_transfer(meta: TraceMeta, data: bytes, rerequested: int) -> TraceTransfer:
    """The int16 codes [n_channels, count] of a READ_TRACES transfer; TransferError if they do not fill them."""
    n_ch = len(channels_of(meta.channel_mask))
    codes = np.frombuffer(data, dtype="<i2").astype(np.int16)
    if n_ch == 0 or codes.size != n_ch * meta.count:
        raise TransferError(f"{codes.size} codes do not fill {n_ch} channels x {meta.count} samples")
    return TraceTransfer(
        meta.measurement_id, meta.boot_id, bool(meta.is_baseline), channels_of(meta.channel_mask),
        meta.start, codes.reshape(n_ch, meta.count), meta.volts_per_code, meta.fs_hz, meta.t0_s,
        meta.temperature_c, meta.adc_bits, meta.transfer_crc32c, rerequested,
        excitation_hz=meta.excitation_hz, cycles=meta.cycles, averaging=meta.averaging,
        record_channels=None if meta.record_channel_mask is None else channels_of(meta.record_channel_mask),
        record_n_samples=meta.record_n_samples,
    )


def di_transfer(meta: DiMeta, data: bytes, rerequested: int) -> DiTransfer:
    """The float32 pixels [n_axial, n_angle] of a READ_DI transfer; TransferError if they do not fill them."""
    pixels = np.frombuffer(data, dtype="<f4").astype(np.float32)
    if pixels.size != meta.n_axial * meta.n_angle:
        raise TransferError(f"{pixels.size} pixels do not fill {meta.n_axial} x {meta.n_angle}")
    grid = Grid(meta.axial_start_mm, meta.axial_step_mm, meta.n_axial,
                meta.angle_start_deg, meta.angle_step_deg, meta.n_angle)
    return DiTransfer(meta.di_id, meta.boot_id, meta.current_id, meta.baseline_id, meta.decimation,
                      grid, pixels.reshape(meta.n_axial, meta.n_angle), meta.transfer_crc32c, rerequested)
