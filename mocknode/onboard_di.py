"""The node's on-board DI map, as docs/protocol.md section 4.6 specifies it (pure): the two records
decimated on board, Algorithm 1 on them in volts, float32 pixels on the requested grid."""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from imaging.dimap import compute_di_map
from imaging.grid import Grid, GridError
from imaging.measurement import Measurement
from mocknode import physics
from protocol.messages import MAX_DI_PIXELS, ComputeDiRequest

DEFAULT_STEP_MM_DEG = 2.0  # the default grid: 2 mm x 2 deg over 0..tx_rx_distance x 0..358 deg
Decimation = Literal["subsample", "boxcar"]


class GridRefused(ValueError):
    """COMPUTE_DI asks for a grid the node does not make (BAD_ARGUMENT)."""


def requested_grid(message: ComputeDiRequest, tx_rx_distance_mm: float) -> Grid:
    """The grid of a COMPUTE_DI request: the default when ``axial_count`` is 0."""
    if message.axial_count == 0:
        return Grid.default(tx_rx_distance_mm, axial_step_mm=DEFAULT_STEP_MM_DEG, angle_step_deg=DEFAULT_STEP_MM_DEG)
    try:
        grid = Grid(message.axial_start_mm, message.axial_step_mm, message.axial_count,
                    message.angle_start_deg, message.angle_step_deg, message.angle_count)
    except GridError as exc:
        raise GridRefused(f"grid: {exc}") from exc
    if grid.axial_count * grid.angle_count > MAX_DI_PIXELS:
        raise GridRefused(f"grid has more than {MAX_DI_PIXELS} pixels")
    return grid


def decimated(record: Measurement, codes: np.ndarray, volts_per_code: float, factor: int,
              method: Decimation = "subsample") -> Measurement:
    """``record`` as the FPGA keeps it for the map: every ``factor``-th code (sample 0 first), in volts."""
    kept = physics.decimate_codes(codes, factor, method=method)
    traces = np.asarray(kept, dtype=np.float64) * volts_per_code
    return dataclasses.replace(record, traces=traces, fs_hz=record.fs_hz / factor)


def onboard_map(baseline: Measurement, current: Measurement, grid: Grid) -> tuple[np.ndarray, tuple[int, int]]:
    """Pixels float32 [n_axial, n_angle] in V^2 and the index of the largest; raises BaselineMismatch."""
    pixels = np.asarray(compute_di_map(baseline, current, grid).pixels, dtype=np.float32)
    axial, angle = np.unravel_index(int(np.argmax(pixels)), pixels.shape)
    return pixels, (int(axial), int(angle))
