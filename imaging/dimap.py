"""Damage-index (DI) maps: the paper's Algorithm 1, literal and fast.

DI(pixel) = sum over receivers m of sum_{k=sn_m}^{sn_m+W-1} (baseline_m[k] - current_m[k])^2,
where sn_m is the window start for the time of flight pixel -> receiver m.

Windows that run past either end of a trace: the samples outside [0, n_samples) do not
exist and contribute nothing (the trace is treated as zero outside the record). A window
entirely outside the record contributes 0 for that receiver.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from imaging.grid import Grid
from imaging.measurement import Measurement
from imaging.timing import MM_PER_M, shortest_path_tof_s, window_starts, wrapped_arc_mm


class BaselineMismatch(ValueError):
    """Baseline and current measurement cannot be compared (different receivers, sampling, geometry)."""


@dataclass(frozen=True)
class DIMap:
    """A DI map: ``pixels`` [n_axial, n_angle] on ``grid``, made by ``method`` with ``window_samples``."""

    pixels: np.ndarray
    grid: Grid
    method: str
    window_samples: int

    @property
    def peak_di(self) -> float:
        return float(self.pixels.max())


def default_window_samples(m: Measurement) -> int:
    """The excitation length cycles/f in samples (588 at 85 kHz, 667 at 75 kHz for 5 cycles at 10 MHz)."""
    return max(1, round(m.cycles / m.excitation_hz * m.fs_hz))


# What "the same geometry" means physically: files written as float32 (an API export) and float64
# (by hand) of one set-up differ by ~1e-7 relative, far below anything a wave could tell apart.
GEOMETRY_TOLERANCE_MM = 0.01  # distances, circumference, and receiver positions as arc on the wall
SAMPLING_RELATIVE_TOLERANCE = 1e-6  # fs_hz
T0_TOLERANCE_SAMPLES = 1e-3  # t0_s, in sample periods


def check_compatible(baseline: Measurement, current: Measurement) -> None:
    """Raise BaselineMismatch unless the two measurements share receivers, sampling and geometry.

    Compared at the precision that matters physically (0.01 mm, 1e-6 of the sampling rate, a
    thousandth of a sample), and the message says by how much they differ in those units."""
    if baseline.traces.shape != current.traces.shape:
        raise BaselineMismatch(
            f"baseline traces {baseline.traces.shape} and current traces {current.traces.shape} differ in shape"
        )
    if not math.isclose(baseline.fs_hz, current.fs_hz, rel_tol=SAMPLING_RELATIVE_TOLERANCE):
        raise BaselineMismatch(f"fs_hz differs: baseline {baseline.fs_hz:.7g} Hz, current {current.fs_hz:.7g} Hz")
    if abs(baseline.t0_s - current.t0_s) * current.fs_hz > T0_TOLERANCE_SAMPLES:
        raise BaselineMismatch(
            f"t0_s differs by {(current.t0_s - baseline.t0_s) * current.fs_hz:+.3g} samples: "
            f"baseline {baseline.t0_s * 1e6:.6g} us, current {current.t0_s * 1e6:.6g} us"
        )
    for name in ("tx_rx_distance_mm", "circumference_mm"):
        a, b = getattr(baseline, name), getattr(current, name)
        if abs(a - b) > GEOMETRY_TOLERANCE_MM:
            raise BaselineMismatch(
                f"{name} differs by {b - a:+.3f} mm: baseline {a:.3f} mm, current {b:.3f} mm "
                f"(tolerance {GEOMETRY_TOLERANCE_MM} mm)"
            )
    arc_mm = wrapped_arc_mm(current.rx_angles_deg, baseline.rx_angles_deg, current.circumference_mm)
    if np.any(arc_mm > GEOMETRY_TOLERANCE_MM):
        k = int(np.argmax(arc_mm))
        raise BaselineMismatch(
            f"receiver angles differ between baseline and current: receiver {k} at {baseline.rx_angles_deg[k]:.3f} deg "
            f"and {current.rx_angles_deg[k]:.3f} deg, {arc_mm[k]:.2f} mm apart on the wall"
        )


def literal_di_map(
    baseline: Measurement, current: Measurement, grid: Grid | None = None, window_samples: int | None = None
) -> np.ndarray:
    """Algorithm 1 as printed, pixel by pixel: the test oracle and the benchmark's reference."""
    check_compatible(baseline, current)
    grid = grid or Grid.default(current.tx_rx_distance_mm)
    w = window_samples or default_window_samples(current)
    n = current.n_samples
    c_mm_s = current.velocity_m_s * MM_PER_M
    out = np.zeros(grid.shape, dtype=np.float64)
    b_traces = baseline.traces.astype(np.float64)
    d_traces = current.traces.astype(np.float64)
    for i, z in enumerate(grid.axial_mm):
        for j, theta in enumerate(grid.angle_deg):
            window_bs, window_dm = [], []
            for m, rx_angle in enumerate(current.rx_angles_deg):
                diff = (theta - rx_angle) % 360.0
                arc = min(diff, 360.0 - diff) * current.circumference_mm / 360.0
                tof = (z + math.hypot(current.tx_rx_distance_mm - z, arc)) / c_mm_s
                sn = math.floor((tof - current.t0_s) * current.fs_hz + 0.5)
                lo, hi = min(max(sn, 0), n), min(max(sn + w, 0), n)
                window_bs.append(b_traces[m, lo:hi])
                window_dm.append(d_traces[m, lo:hi])
            delta = np.concatenate(window_bs) - np.concatenate(window_dm)
            out[i, j] = float(np.sum(delta * delta))
    return out


@lru_cache(maxsize=16)
def _gather_table(
    grid: Grid,
    rx_angles_deg: tuple[float, ...],
    tx_rx_distance_mm: float,
    circumference_mm: float,
    velocity_m_s: float,
    t0_s: float,
    fs_hz: float,
) -> tuple[np.ndarray, int, int]:
    """Window starts for every receiver and pixel, as offsets into a flat per-receiver energy table.

    Returns (index [n_rx, n_pixels] int32, k_min, n_starts): receiver m's energy for start k
    lives at m * n_starts + (k - k_min). Cached per geometry: the same node images with the
    same table every time.
    """
    tof = shortest_path_tof_s(grid, np.array(rx_angles_deg), tx_rx_distance_mm, circumference_mm, velocity_m_s)
    sn = window_starts(tof, t0_s, fs_hz).reshape(len(rx_angles_deg), -1)
    k_min, k_max = int(sn.min()), int(sn.max())
    n_starts = k_max - k_min + 1
    offsets = (np.arange(len(rx_angles_deg), dtype=np.int64) * n_starts)[:, None]
    index = (sn - k_min + offsets).astype(np.int32)
    index.setflags(write=False)
    return index, k_min, n_starts


def windowed_energy(residual: np.ndarray, window_samples: int, k_min: int, n_starts: int) -> np.ndarray:
    """sum(residual[m, k:k+W]**2) for every receiver m and start k in [k_min, k_min+n_starts), zero outside.

    The squared residual is laid out from sample k_min in blocks of exactly W samples, so any
    window is a suffix of one block plus a prefix of the next. Both are sums of non-negative
    terms: no difference of large partial sums, so a quiet window after a loud direct arrival
    keeps full relative accuracy (error <= W * float64 epsilon).
    """
    n_rx, n = residual.shape
    w = window_samples
    n_blocks = -(-(n_starts + w) // w)
    padded = np.zeros((n_rx, n_blocks * w), dtype=np.float64)
    src_lo, src_hi = max(k_min, 0), min(k_min + n_blocks * w, n)
    if src_hi > src_lo:
        padded[:, src_lo - k_min : src_hi - k_min] = np.square(residual[:, src_lo:src_hi], dtype=np.float64)
    blocks = padded.reshape(n_rx, n_blocks, w)
    suffix = np.cumsum(blocks[:, :, ::-1], axis=2)[:, :, ::-1].reshape(n_rx, -1)
    prefix = np.zeros_like(blocks)
    np.cumsum(blocks[:, :, :-1], axis=2, out=prefix[:, :, 1:])
    flat_prefix = prefix.reshape(n_rx, -1)
    return suffix[:, :n_starts] + flat_prefix[:, w : w + n_starts]


def compute_di_map(
    baseline: Measurement,
    current: Measurement,
    grid: Grid | None = None,
    *,
    window_samples: int | None = None,
) -> DIMap:
    """Algorithm 1, fast: per-receiver windowed residual energies gathered through a cached index table."""
    check_compatible(baseline, current)
    return paper_di_map(baseline, current, grid, window_samples=window_samples)


def paper_di_map(baseline: Measurement, current: Measurement, grid: Grid | None = None, *,
                 window_samples: int | None = None) -> DIMap:
    """``compute_di_map`` of a pair already known compatible (``check_compatible``)."""
    grid = grid or Grid.default(current.tx_rx_distance_mm)
    w = window_samples or default_window_samples(current)
    index, k_min, n_starts = _gather_table(
        grid,
        tuple(float(a) for a in current.rx_angles_deg),
        current.tx_rx_distance_mm,
        current.circumference_mm,
        current.velocity_m_s,
        current.t0_s,
        current.fs_hz,
    )
    residual = baseline.traces.astype(np.float64) - current.traces.astype(np.float64)
    energy = windowed_energy(residual, w, k_min, n_starts).ravel()
    pixels = np.take(energy, index[0])
    for m in range(1, index.shape[0]):
        pixels += np.take(energy, index[m])
    return DIMap(pixels.reshape(grid.shape), grid, "paper", w)


__all__ = [
    "BaselineMismatch",
    "DIMap",
    "check_compatible",
    "compute_di_map",
    "default_window_samples",
    "literal_di_map",
    "paper_di_map",
    "windowed_energy",
    "wrapped_arc_mm",
]
