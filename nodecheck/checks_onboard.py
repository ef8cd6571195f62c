"""Checks of the on-board DI map and of absent capabilities: R-DI-1, R-DI-2, R-CAP-1."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imaging.dimap import compute_di_map
from imaging.grid import Grid
from imaging.measurement import Measurement
from nodecheck.context import Context, Record
from nodecheck.outcomes import NotApplicable, expect
from protocol.crc import crc32c
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_CHUNK_RETRANSMIT,
    CAP_ON_BOARD_DI,
    CAPABILITY_NAMES,
    MAX_DI_PIXELS,
    AcquireRequest,
    ComputeDiReply,
    ComputeDiRequest,
    DiMeta,
    ErrorCode,
    ReadDiRequest,
    ReadTracesRequest,
)

DI_TOLERANCE = 1e-3  # of the map's peak: float32 pixels, a float32 volts_per_code
_CUSTOM_GRID = Grid(100.0, 5.0, 41, 10.0, 10.0, 36)


@dataclass(frozen=True)
class OnBoardMap:
    baseline: Record
    current: Record
    reply: ComputeDiReply
    grid: Grid
    pixels: np.ndarray


def _pair(ctx: Context) -> tuple[Record, Record, int]:
    """A baseline and a current measurement read in full; the baseline id to ask COMPUTE_DI for (0: the slot)."""
    ctx.configure()
    if ctx.has(CAP_BASELINE_SLOT):
        baseline = ctx.read_record(ctx.acquire(as_baseline=1))
        asked = 0
    else:
        baseline = ctx.read_record(ctx.acquire())
        asked = baseline.acquired.measurement_id
    return baseline, ctx.read_record(ctx.acquire()), asked


def _read_map(ctx: Context, computed: ComputeDiReply, what: str) -> tuple[DiMeta, np.ndarray]:
    bulk = ctx.read(ReadDiRequest(computed.di_id), DiMeta, f"READ_DI of {what}")
    meta = bulk.meta
    assert isinstance(meta, DiMeta)
    data = bulk.data
    expect(len(data) == meta.total_bytes == 4 * meta.n_axial * meta.n_angle and crc32c(data) == meta.transfer_crc32c,
           f"READ_DI of {what}: {len(data)} bytes, META {meta.total_bytes} for {meta.n_axial}x{meta.n_angle}, "
           f"CRC 0x{crc32c(data):08X} vs 0x{meta.transfer_crc32c:08X}", bulk.reply.evidence())
    fields = (meta.di_id, meta.current_id, meta.baseline_id, meta.decimation, meta.n_axial, meta.n_angle, meta.boot_id)
    said = (computed.di_id, computed.current_id, computed.baseline_id, computed.decimation, computed.n_axial,
            computed.n_angle, ctx.node.boot_id)
    expect(fields == said, f"DI_META {fields} != COMPUTE_DI_REPLY {said}", bulk.reply.evidence())
    return meta, np.frombuffer(data, dtype="<f4").reshape(meta.n_axial, meta.n_angle)


def check_di(ctx: Context) -> NotApplicable | str:
    if not ctx.has(CAP_ON_BOARD_DI):
        return NotApplicable("capability ON_BOARD_DI absent")
    baseline, current, asked = _pair(ctx)
    timeout_s = ctx.session.timing.compute_timeout_s
    reply = ctx.ask(ComputeDiRequest(current.acquired.measurement_id, asked), timeout_s=timeout_s)
    computed = ctx.expect_message(reply, ComputeDiReply, "COMPUTE_DI on the default grid")
    default = Grid.default(ctx.node.tx_rx_distance_mm, axial_step_mm=2.0, angle_step_deg=2.0)
    ids = (computed.current_id, computed.baseline_id, computed.decimation, computed.n_axial, computed.n_angle)
    want = (current.acquired.measurement_id, baseline.acquired.measurement_id, ctx.node.decimation,
            default.axial_count, default.angle_count)
    expect(ids == want, f"COMPUTE_DI_REPLY (current, baseline, decimation, n_axial, n_angle) {ids}, expected {want}",
           reply.evidence())
    meta, pixels = _read_map(ctx, computed, "the default map")
    grid = Grid(meta.axial_start_mm, meta.axial_step_mm, meta.n_axial, meta.angle_start_deg, meta.angle_step_deg,
                meta.n_angle)
    expect(grid == default, f"the default grid is {grid}, expected {default}")
    peak = np.unravel_index(int(np.argmax(pixels)), pixels.shape)
    expect(np.float32(computed.peak_value) == pixels[peak]
           and np.isclose(computed.peak_axial_mm, grid.axial_mm[peak[0]])
           and np.isclose(computed.peak_angle_deg, grid.angle_deg[peak[1]]),
           f"peak {computed.peak_value} at {computed.peak_axial_mm} mm/{computed.peak_angle_deg} deg; the map's maximum "
           f"is {pixels[peak]} at {grid.axial_mm[peak[0]]} mm/{grid.angle_deg[peak[1]]} deg")
    ctx.notes["di"] = OnBoardMap(baseline, current, computed, grid, pixels.astype(np.float64))
    g = _CUSTOM_GRID
    custom = ctx.expect_message(ctx.ask(ComputeDiRequest(
        current.acquired.measurement_id, asked, 5, g.axial_start_mm, g.axial_step_mm, g.axial_count,
        g.angle_start_deg, g.angle_step_deg, g.angle_count), timeout_s=timeout_s), ComputeDiReply,
        "COMPUTE_DI on a requested grid, decimation 5")
    meta, _ = _read_map(ctx, custom, "the requested grid")
    got = Grid(meta.axial_start_mm, meta.axial_step_mm, meta.n_axial, meta.angle_start_deg, meta.angle_step_deg,
               meta.n_angle)
    expect(got == g and meta.decimation == 5, f"a {g} map at decimation 5 came back as {got}, decimation "
           f"{meta.decimation}")
    side = math.isqrt(MAX_DI_PIXELS) + 1
    too_big = ComputeDiRequest(current.acquired.measurement_id, asked, 0, 0.0, 1.0, side, 0.0, 1.0, side)
    ctx.expect_error(ctx.ask(too_big, timeout_s=timeout_s), ErrorCode.BAD_ARGUMENT,
                     f"a {side} x {side} pixel grid (over {MAX_DI_PIXELS})")
    ctx.expect_error(ctx.ask(ReadDiRequest(0xFFFFFFF0)), ErrorCode.NO_SUCH_DI, "READ_DI of map 0xFFFFFFF0")
    ctx.expect_error(ctx.ask(ComputeDiRequest(0xFFFFFFF0, asked), timeout_s=timeout_s),
                     ErrorCode.NO_SUCH_MEASUREMENT, "COMPUTE_DI of measurement 0xFFFFFFF0")
    return f"{default.axial_count} x {default.angle_count} pixels, decimation {computed.decimation}"


def _subsampled(ctx: Context, record: Record, factor: int) -> Measurement:
    meta, info = record.meta, ctx.node
    rx = np.asarray(info.rx_angles_deg, dtype=np.float64)[[i for i in range(32) if meta.channel_mask >> i & 1]]
    return Measurement(
        traces=record.codes[:, ::factor].astype(np.float64) * meta.volts_per_code,
        fs_hz=meta.fs_hz / factor, t0_s=meta.t0_s, rx_angles_deg=rx,
        tx_angles_deg=np.asarray(info.tx_angles_deg, dtype=np.float64), tx_rx_distance_mm=info.tx_rx_distance_mm,
        circumference_mm=info.circumference_mm, velocity_m_s=info.velocity_m_s,
        excitation_hz=float(record.acquired.excitation_hz or ctx.settings().excitation_hz),
        cycles=int(record.acquired.cycles or ctx.settings().cycles),
    )


def check_di_values(ctx: Context) -> NotApplicable | str:
    if not ctx.has(CAP_ON_BOARD_DI):
        return NotApplicable("capability ON_BOARD_DI absent")
    board = ctx.notes.get("di")
    expect(isinstance(board, OnBoardMap), "no on-board map to compare (R-DI-1 failed)")
    assert isinstance(board, OnBoardMap)
    factor = board.reply.decimation
    expected = compute_di_map(_subsampled(ctx, board.baseline, factor), _subsampled(ctx, board.current, factor),
                              board.grid).pixels
    scale = max(float(np.abs(expected).max()), 1e-30)
    error = float(np.abs(board.pixels - expected).max()) / scale
    where = np.unravel_index(int(np.argmax(np.abs(board.pixels - expected))), expected.shape)
    expect(error <= DI_TOLERANCE, f"the node's map differs from Algorithm 1 on every {factor}th sample by "
           f"{error:.3g} of its peak (pixel {tuple(int(i) for i in where)}: {board.pixels[where]:.6g} vs "
           f"{expected[where]:.6g} V^2)")
    return f"largest difference {error:.1e} of the peak"


def check_absent_capabilities(ctx: Context) -> NotApplicable | str:
    absent = [cap for cap in CAPABILITY_NAMES if not ctx.has(cap)]
    if not absent:
        return NotApplicable("every capability is present")
    if CAP_ON_BOARD_DI in absent:
        for request in (ComputeDiRequest(1), ReadDiRequest(1)):
            ctx.expect_error(ctx.ask(request), ErrorCode.UNKNOWN_COMMAND, f"{type(request).__name__} without ON_BOARD_DI")
    if CAP_BASELINE_SLOT in absent:
        expected = ctx.acquire().measurement_id + 1
        ctx.expect_error(ctx.ask(AcquireRequest(1)), ErrorCode.BAD_ARGUMENT, "ACQUIRE(as_baseline=1) without "
                         "BASELINE_SLOT")
        got = ctx.acquire().measurement_id
        expect(got == expected and ctx.status().baseline_id == 0, f"the refused baseline ACQUIRE ran (next id {got}, "
               f"expected {expected}) or a baseline is held")
    if CAP_CHUNK_RETRANSMIT in absent:
        acquired = ctx.acquire()
        read = ReadTracesRequest(acquired.measurement_id, acquired.channel_mask, 0, 0, (0,))
        ctx.expect_error(ctx.ask(read), ErrorCode.BAD_ARGUMENT, "a chunk list without CHUNK_RETRANSMIT")
    return "absent: " + ", ".join(CAPABILITY_NAMES[c] for c in absent)
