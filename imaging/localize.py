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


def parabolic_offset(left: float, centre: float, right: float) -> float:
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
        axial += grid.axial_step_mm * parabolic_offset(px[i - 1, j], px[i, j], px[i + 1, j])
    angle = grid.angle_start_deg + grid.angle_step_deg * j
    if grid.wraps_in_angle and n_angle >= 3:
        left, right = px[i, (j - 1) % n_angle], px[i, (j + 1) % n_angle]
        angle += grid.angle_step_deg * parabolic_offset(left, px[i, j], right)
    elif 0 < j < n_angle - 1:
        angle += grid.angle_step_deg * parabolic_offset(px[i, j - 1], px[i, j], px[i, j + 1])
    return Estimate(float(axial), float(np.mod(angle, 360.0)), float(px[i, j]))


def locate_peak(di_map: DIMap) -> Estimate:
    """The strongest pixel of the map, refined below the grid spacing."""
    i, j = np.unravel_index(int(np.argmax(di_map.pixels)), di_map.pixels.shape)
    return refine_peak(di_map, int(i), int(j))


@dataclass(frozen=True)
class Confidence:
    """How much to trust a peak: ``peak_ratio`` = second-highest local peak (outside ``exclusion_mm``)
    over the highest, the -3 dB widths of the main peak, and ``score`` = 1 - peak_ratio in [0, 1]."""

    peak_ratio: float
    width_axial_mm: float
    width_angle_deg: float
    score: float

    def as_dict(self) -> dict:
        return {
            "score": self.score,
            "peak_ratio": self.peak_ratio,
            "width_axial_mm": self.width_axial_mm,
            "width_angle_deg": self.width_angle_deg,
        }


def _half_power_width(profile: np.ndarray, k: int, step: float, wraps: bool) -> float:
    """Width (in units of ``step``) of the contiguous run around k above profile[k] / sqrt(2)."""
    level = profile[k] / np.sqrt(2.0)
    n = profile.size
    count = 1
    for direction in (-1, 1):
        for step_i in range(1, n):  # bounded by the profile length
            idx = k + direction * step_i
            if wraps:
                idx %= n
            elif not 0 <= idx < n:
                break
            if profile[idx] < level or count >= n:
                break
            count += 1
    return float(count * step)


def exclusion_mask(grid, axial_mm: float, angle_deg: float, radius_mm: float, circumference_mm: float) -> np.ndarray:
    """Pixels within ``radius_mm`` (surface distance, wrap-aware) of a point: True inside."""
    dz = grid.axial_mm[:, None] - axial_mm
    diff = np.mod(grid.angle_deg[None, :] - angle_deg, 360.0)
    arc = np.minimum(diff, 360.0 - diff) * circumference_mm / 360.0
    return np.hypot(dz, arc) <= radius_mm


def peak_confidence(di_map: DIMap, estimate: Estimate, *, circumference_mm: float, exclusion_mm: float = 50.0,
                    runner_up_di: float | None = None) -> Confidence:
    """Confidence of ``estimate`` on ``di_map``: competing-peak ratio and main-lobe widths.

    ``runner_up_di``: the competing peak's DI refined off the map's pixels, when the estimate
    was (so both sides of the ratio are sampled alike; imaging/multidefect.py)."""
    px, grid = di_map.pixels, di_map.grid
    i = int(np.clip(round((estimate.axial_mm - grid.axial_start_mm) / grid.axial_step_mm), 0, grid.axial_count - 1))
    j = round((estimate.angle_deg - grid.angle_start_deg) / grid.angle_step_deg)
    j = j % grid.angle_count if grid.wraps_in_angle else int(np.clip(j, 0, grid.angle_count - 1))
    # The estimate's own DI when it was refined off the map's pixels (a finer local grid).
    peak = max(float(px[i, j]), float(estimate.di))
    outside = ~exclusion_mask(grid, estimate.axial_mm, estimate.angle_deg, exclusion_mm, circumference_mm)
    second = float(px[outside].max()) if outside.any() else 0.0
    if runner_up_di is not None:
        second = max(second, float(runner_up_di))
    ratio = float(np.clip(second / peak, 0.0, 1.0)) if peak > 0 else 1.0
    width_axial = _half_power_width(px[:, j], i, grid.axial_step_mm, False)
    width_angle = _half_power_width(px[i, :], j, grid.angle_step_deg, grid.wraps_in_angle)
    return Confidence(ratio, width_axial, width_angle, 1.0 - ratio)
