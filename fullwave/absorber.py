"""Absorbing pipe ends: a convolutional perfectly matched layer (CPML) beyond each end.

The pipe continues past each absorbing end into a layer of the same wall in which the axial
derivative is stretched, d/dz -> d/dz / s_z with s_z = 1 + d(x) / (alpha(x) + i omega)
(complex-frequency-shifted PML; Roden & Gedney 2000, Komatitsch & Martin 2007). In the time
domain every axial derivative in the layer carries a memory variable

    psi^n = b psi^(n-1) + a (du/dz)^n,     du/dz -> du/dz + psi,
    b = exp(-(d + alpha) dt),  a = d (b - 1) / (d + alpha),

with the damping d(x) = d0 (x / L)^2 growing from 0 at the pipe end to d0 at the layer's outer
edge (depth x, thickness L), d0 = 3 c ln(1 / R0) / (2 L), and alpha(x) = alpha0 (1 - x / L). The
layer's outer edge is a free end; what little reaches it is damped again on the way back.
Only z is stretched: the circumference stays periodic. The reflection measured on the grid
(docs/fullwave.md) is what matters, not R0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullwave.grid import Grid

THEORETICAL_REFLECTION = 1e-4  # R0 of the continuous layer at normal incidence
DAMPING_ORDER = 2


@dataclass(frozen=True)
class Cpml:
    """Memory-variable coefficients at cells [nz] and at faces [nz + 1] (0 outside the layers)."""

    a_cell: np.ndarray
    b_cell: np.ndarray
    a_face: np.ndarray
    b_face: np.ndarray

    def astype(self, dtype: type) -> Cpml:
        """The coefficients as contiguous arrays of the kernels' ``dtype``."""
        return Cpml(*(np.ascontiguousarray(a, dtype=dtype) for a in (self.a_cell, self.b_cell, self.a_face,
                                                                        self.b_face)))


def _depth_fraction(z_m: np.ndarray, grid: Grid) -> np.ndarray:
    """Depth into the nearer layer as a fraction of its thickness (0 inside the pipe)."""
    thickness = grid.pml_cells * grid.dz_m
    if thickness == 0:
        return np.zeros_like(z_m)
    beyond = np.maximum(-z_m, z_m - grid.length_m)
    return np.clip(beyond / thickness, 0.0, 1.0)


def _coefficients(x: np.ndarray, thickness_m: float, velocity_m_s: float, frequency_hz: float,
                  dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    d0 = (DAMPING_ORDER + 1) * velocity_m_s * math.log(1 / THEORETICAL_REFLECTION) / (2 * thickness_m)
    d = d0 * x**DAMPING_ORDER
    alpha = math.pi * frequency_hz * (1 - x)
    b = np.exp(-(d + alpha) * dt_s)
    a = np.divide(d * (b - 1), d + alpha, out=np.zeros_like(d), where=d > 0)
    return a, np.where(d > 0, b, 0.0)


def cpml(grid: Grid, velocity_m_s: float, frequency_hz: float, dt_s: float) -> Cpml:
    """The layer's coefficients for waves up to ``velocity_m_s`` around ``frequency_hz``."""
    if grid.pml_cells == 0:
        zeros_c, zeros_f = np.zeros(grid.nz), np.zeros(grid.nz + 1)
        return Cpml(zeros_c, zeros_c, zeros_f, zeros_f)
    thickness = grid.pml_cells * grid.dz_m
    a_c, b_c = _coefficients(_depth_fraction(grid.cell_z_m(), grid), thickness, velocity_m_s, frequency_hz, dt_s)
    a_f, b_f = _coefficients(_depth_fraction(grid.face_z_m(), grid), thickness, velocity_m_s, frequency_hz, dt_s)
    return Cpml(a_c, b_c, a_f, b_f)


__all__ = ["DAMPING_ORDER", "THEORETICAL_REFLECTION", "Cpml", "cpml"]
