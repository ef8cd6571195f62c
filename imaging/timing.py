"""Time of flight from the Tx ring to a pixel and on to each receiver (the paper's model).

The Tx ring fires all transducers at once, so the wave reaching a pixel is an axisymmetric
torsional front: d_tx is the axial distance only. The scattered wave travels from the
pixel to the receiver along the shortest line on the unrolled (periodic) pipe wall.
"""
from __future__ import annotations

import numpy as np

from imaging.grid import Grid

MM_PER_M = 1000.0


def wrapped_arc_mm(angle_a_deg: np.ndarray, angle_b_deg: np.ndarray, circumference_mm: float) -> np.ndarray:
    """Shortest circumferential distance between two angles, going either way round."""
    diff = np.mod(np.asarray(angle_a_deg, dtype=np.float64) - np.asarray(angle_b_deg, dtype=np.float64), 360.0)
    return np.minimum(diff, 360.0 - diff) * (circumference_mm / 360.0)


def surface_distance_mm(
    axial_a_mm: float, angle_a_deg: float, axial_b_mm: float, angle_b_deg: float, circumference_mm: float
) -> float:
    """Distance between two points on the unrolled pipe wall, wrap-aware in angle.

    This is the localization-error metric: 0 for the true position, and a defect at 359 deg
    estimated at 1 deg is 2 deg of arc away, not 358.
    """
    arc = float(wrapped_arc_mm(np.array(angle_a_deg), np.array(angle_b_deg), circumference_mm))
    return float(np.hypot(axial_a_mm - axial_b_mm, arc))


def shortest_path_tof_s(
    grid: Grid,
    rx_angles_deg: np.ndarray,
    tx_rx_distance_mm: float,
    circumference_mm: float,
    velocity_m_s: float,
) -> np.ndarray:
    """T_tof = (d_tx + d_rx) / C for every receiver and pixel, shape [n_rx, n_axial, n_angle], seconds."""
    axial = grid.axial_mm[None, :, None]
    arc = wrapped_arc_mm(grid.angle_deg[None, None, :], np.asarray(rx_angles_deg)[:, None, None], circumference_mm)
    d_rx = np.hypot(tx_rx_distance_mm - axial, arc)
    return (axial + d_rx) / (velocity_m_s * MM_PER_M)


def window_starts(tof_s: np.ndarray, t0_s: float, fs_hz: float) -> np.ndarray:
    """Window start sample sn = round((T_tof - t0) * fs), rounding halves up, as int64."""
    return np.floor((tof_s - t0_s) * fs_hz + 0.5).astype(np.int64)
