"""Defect position from a DI map: the arg-max pixel, refined below the grid spacing."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imaging.dimap import DIMap


@dataclass(frozen=True)
class Estimate:
    """An estimated defect position: ``axial_mm`` from the Tx ring, ``angle_deg`` in [0, 360)."""

    axial_mm: float
    angle_deg: float
    di: float

    def as_dict(self) -> dict:
        return {"axial_mm": self.axial_mm, "angle_deg": self.angle_deg, "di": self.di}


def _parabolic_offset(left: float, centre: float, right: float) -> float:
    """Vertex of the parabola through three equally spaced samples, in steps from the centre, in [-0.5, 0.5]."""
    curvature = left - 2.0 * centre + right
    if curvature >= 0.0:  # not a strict maximum (flat or a valley): keep the pixel centre
        return 0.0
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


def refine_peak(di_map: DIMap, i: int, j: int) -> Estimate:
    """Refine pixel (i, j) by a separable quadratic fit on its neighbours (wrap-aware in angle)."""
    px, grid = di_map.pixels, di_map.grid
    n_axial, n_angle = px.shape
    axial = grid.axial_start_mm + grid.axial_step_mm * i
    if 0 < i < n_axial - 1:
        axial += grid.axial_step_mm * _parabolic_offset(px[i - 1, j], px[i, j], px[i + 1, j])
    angle = grid.angle_start_deg + grid.angle_step_deg * j
    if grid.wraps_in_angle and n_angle >= 3:
        left, right = px[i, (j - 1) % n_angle], px[i, (j + 1) % n_angle]
        angle += grid.angle_step_deg * _parabolic_offset(left, px[i, j], right)
    elif 0 < j < n_angle - 1:
        angle += grid.angle_step_deg * _parabolic_offset(px[i, j - 1], px[i, j], px[i, j + 1])
    return Estimate(float(axial), float(np.mod(angle, 360.0)), float(px[i, j]))


def locate_peak(di_map: DIMap) -> Estimate:
    """The strongest pixel of the map, refined below the grid spacing."""
    i, j = np.unravel_index(int(np.argmax(di_map.pixels)), di_map.pixels.shape)
    return refine_peak(di_map, int(i), int(j))
