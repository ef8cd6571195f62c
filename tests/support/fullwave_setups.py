"""Small full-wave experiments for the physics tests: a strip of pipe wall, a source, receivers.

A *line* experiment drives the whole circumference at once (an axisymmetric T(0,1) plane wave)
on a strip a few cells round, so it is cheap and its theory is one-dimensional. Pulse timing
is read from the Hilbert envelope's peak, refined by a parabola through its top three samples.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import hilbert

from fullwave import inplane, sh
from fullwave.absorber import cpml
from fullwave.defects import apply_defects
from fullwave.dispersion import stable_dt_s
from fullwave.grid import Grid, make_grid, rectangle_coverage
from fullwave.medium import Medium, Steel, modulus_scale, uniform_medium
from fullwave.transducers import PatchWeights, averaging_weights, forcing_weights, tone_burst

STEEL = Steel()
C_T = STEEL.shear_velocity_m_s  # sqrt(mu / rho) from E, nu, rho: the theory every timing test uses
WALL_M = 0.004
MM = 1e-3


@dataclass
class Run:
    t_s: np.ndarray  # receiver sample times (half steps)
    out: np.ndarray  # [n_steps, n_rx]
    grid: Grid
    medium: Medium
    op: sh.ShOperator
    state: sh.ShState
    dt_s: float


def wall(length_mm: float, circumference_mm: float, cell_mm: float, ends: str, defects=(), temperature_c=20.0,
         absorber_mm: float = 80.0) -> Medium:
    grid = make_grid(length_mm, circumference_mm, cell_mm, absorber_mm if ends == "absorbing" else 0.0)
    factor = modulus_scale(temperature_c, 20.0, -1e-4)
    return apply_defects(uniform_medium(grid, WALL_M, STEEL, factor), tuple(defects), 0.0, STEEL.density_kg_m3)


def ring_band(grid: Grid, z_mm: float, width_mm: float) -> np.ndarray:
    """Coverage of a band round the whole circumference, ``width_mm`` long, centred at ``z_mm``."""
    half = width_mm * MM / 2
    return rectangle_coverage(grid, z_mm * MM - half, z_mm * MM + half, 0.0, grid.circumference_m)


def patch(grid: Grid, z_mm: float, s_mm: float, size_mm: float = 15.0) -> np.ndarray:
    half = size_mm * MM / 2
    return rectangle_coverage(grid, z_mm * MM - half, z_mm * MM + half, s_mm * MM - half, s_mm * MM + half)


def run(medium: Medium, source: PatchWeights, receivers: PatchWeights, n_rx: int, duration_s: float,
        frequency_hz: float = 85e3, dtype=np.float64, courant: float = 0.9) -> Run:
    grid = medium.grid
    c = medium.max_shear_velocity_m_s
    dt = stable_dt_s(grid.dz_m, grid.ds_m, c, courant)
    op = sh.sh_operator(medium, dt, cpml(grid, c, frequency_hz, dt), dtype)
    state = sh.ShState.zeros(grid.nz, grid.ns, dtype)
    n = int(duration_s / dt)
    out = sh.run(op, state, tone_burst(np.arange(n) * dt, frequency_hz, 5), source, receivers, n_rx)
    return Run((np.arange(n) + 0.5) * dt, out, grid, medium, op, state, dt)


def line(length_mm: float, source_mm: float, receivers_mm: list[float], ends: str = "reflecting",
         defects=(), duration_s: float = 600e-6, frequency_hz: float = 85e3, cell_mm: float = 1.0,
         temperature_c: float = 20.0) -> Run:
    """A T(0,1) plane wave from a 1-cell band at ``source_mm``, sensed by 1-cell bands."""
    medium = wall(length_mm, 4 * cell_mm, cell_mm, ends, defects, temperature_c)
    grid = medium.grid
    source = forcing_weights(ring_band(grid, source_mm, cell_mm))
    receivers = averaging_weights([ring_band(grid, z, cell_mm) for z in receivers_mm])
    return run(medium, source, receivers, len(receivers_mm), duration_s, frequency_hz)


def envelope_peak(t_s: np.ndarray, x: np.ndarray, lo_s: float, hi_s: float) -> tuple[float, float]:
    """(time, height) of the highest point of the envelope of ``x`` cut to lo..hi."""
    env = np.abs(hilbert(window(t_s, x, lo_s, hi_s)))
    inside = np.flatnonzero((t_s >= lo_s) & (t_s <= hi_s))
    k = inside[np.argmax(env[inside])]
    y0, y1, y2 = env[k - 1], env[k], env[k + 1]
    shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    return float(t_s[k] + shift * (t_s[1] - t_s[0])), float(y1 - 0.25 * (y0 - y2) * shift)


def window(t_s: np.ndarray, x: np.ndarray, lo_s: float, hi_s: float) -> np.ndarray:
    return np.where((t_s >= lo_s) & (t_s <= hi_s), x, 0.0)


def pulse_s(frequency_hz: float = 85e3, cycles: int = 5) -> float:
    return cycles / frequency_hz


def band(grid: Grid, z_mm: float, width_mm: float, on_faces: bool = False, s_offset: float = 0.0) -> np.ndarray:
    """``ring_band`` on one of the in-plane model's staggered grids."""
    half = width_mm * MM / 2
    return rectangle_coverage(grid, z_mm * MM - half, z_mm * MM + half, 0.0, grid.circumference_m, on_faces,
                              s_offset)


def box(grid: Grid, z_mm: float, s_mm: float, size_mm: float, on_faces: bool = False,
        s_offset: float = 0.0) -> np.ndarray:
    half = size_mm * MM / 2
    return rectangle_coverage(grid, z_mm * MM - half, z_mm * MM + half, s_mm * MM - half, s_mm * MM + half,
                              on_faces, s_offset)


@dataclass
class InplaneRun:
    t_s: np.ndarray
    out: np.ndarray  # [n_steps, n_rx]
    grid: Grid
    op: inplane.InplaneOperator
    state: inplane.InplaneState
    dt_s: float


def inplane_transducers(grid: Grid, source_z: np.ndarray | None, source_s: np.ndarray | None,
                        receivers: list[tuple[np.ndarray | None, np.ndarray | None]]) -> inplane.Transducers:
    """Traction patterns on the v_z grid (faces) and the v_s grid (cells, half a cell on in s), None for
    no traction along that axis; each receiver averages (axial coverage, circumferential coverage) and
    adds the two (None: it does not sense that axis)."""
    faces, cells = (grid.nz + 1, grid.ns), (grid.nz, grid.ns)
    return inplane.Transducers(
        forcing_weights(source_z if source_z is not None else np.zeros(faces)),
        forcing_weights(source_s if source_s is not None else np.zeros(cells)),
        _sensing([cz for cz, _ in receivers]), _sensing([cs for _, cs in receivers]), len(receivers))


def _sensing(coverages: list[np.ndarray | None]) -> PatchWeights:
    parts = [(row, averaging_weights([c])) for row, c in enumerate(coverages) if c is not None]
    if not parts:
        return PatchWeights(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64))
    return PatchWeights(np.concatenate([w.index for _, w in parts]), np.concatenate([w.weight for _, w in parts]),
                        np.concatenate([np.full(w.index.size, row) for row, w in parts]))


def inplane_run(medium: Medium, transducers: inplane.Transducers, duration_s: float, frequency_hz: float = 85e3,
                dtype=np.float64) -> InplaneRun:
    grid = medium.grid
    c = medium.max_velocity_m_s
    dt = stable_dt_s(grid.dz_m, grid.ds_m, c, 0.9)
    op = inplane.inplane_operator(medium, dt, cpml(grid, c, frequency_hz, dt), dtype)
    state = inplane.InplaneState.zeros(grid.nz, grid.ns, dtype)
    n = int(duration_s / dt)
    out = inplane.run(op, state, tone_burst(np.arange(n) * dt, frequency_hz, 5), transducers)
    return InplaneRun((np.arange(n) + 0.5) * dt, out, grid, op, state, dt)
