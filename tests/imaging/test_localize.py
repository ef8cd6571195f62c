"""Localization: the arg-max pixel refined below the grid spacing, wrap-aware in angle."""
import numpy as np
import pytest

from imaging.analysis import analyze
from imaging.dimap import DIMap
from imaging.grid import Grid
from imaging.localize import locate_peak
from imaging.timing import surface_distance_mm
from tests.support.synthetic import CIRCUMFERENCE_MM, baseline_and_scatterer


@pytest.mark.parametrize(
    "axial_mm, angle_deg",
    [(100, 90), (200, 90), (300, 90), (200, 0), (200, 157.5), (200, 315), (137.3, 251.7), (250, 359.5), (20, 45)],
)
def test_point_scatterer_is_localized_within_5_mm(axial_mm, angle_deg):
    # Noise-free: the paper's energy window is a broad plateau, so with noise its peak wanders
    # (tens of mm at 1 % noise); the noise-robust methods are tested in their own module.
    base, cur = baseline_and_scatterer(axial_mm, angle_deg)
    est = analyze(base, cur).defects[0]
    assert surface_distance_mm(est.axial_mm, est.angle_deg, axial_mm, angle_deg, CIRCUMFERENCE_MM) < 5.0


def _gaussian_map(axial0, angle0, grid):
    a = grid.axial_mm[:, None]
    d = np.mod(grid.angle_deg[None, :] - angle0 + 180.0, 360.0) - 180.0
    return DIMap(np.exp(-((a - axial0) ** 2) / 50.0 - d**2 / 20.0), grid, "test", 1)


@pytest.mark.parametrize("axial0, angle0", [(123.4, 56.7), (200.0, 0.3), (50.5, 359.6), (10.25, 180.5)])
def test_refinement_recovers_sub_pixel_peak(axial0, angle0):
    grid = Grid.default(400.0)
    est = locate_peak(_gaussian_map(axial0, angle0, grid))
    assert est.axial_mm == pytest.approx(axial0, abs=0.1)
    assert surface_distance_mm(est.axial_mm, est.angle_deg, axial0, angle0, 360.0) < 0.15
    assert 0.0 <= est.angle_deg < 360.0


def test_peak_on_the_axial_edge_stays_on_the_grid():
    grid = Grid.default(400.0)
    est = locate_peak(_gaussian_map(-3.0, 90.0, grid))
    assert est.axial_mm == 0.0


def test_surface_distance_wraps_round_the_circumference():
    assert surface_distance_mm(0, 359, 0, 1, 360.0) == pytest.approx(2.0)
    assert surface_distance_mm(0, 0, 3, 0, 360.0) == pytest.approx(3.0)
    assert surface_distance_mm(0, 180, 0, 0, 360.0) == pytest.approx(180.0)
