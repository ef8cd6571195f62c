"""The 90 % localization region: as wide as the map's main lobe says, and an honest flag when it says nothing."""
import pytest

from imaging.localize import Confidence
from imaging.pipeline import AssessSettings, assess
from imaging.region import AXIAL_FLOOR_MM, CIRC_FLOOR_MM, Region, localization_region
from imaging.timing import surface_distance_mm
from tests.support.synthetic import CIRCUMFERENCE_MM, baseline_and_scatterers


def _confidence(peak_ratio=0.5, width_axial_mm=50.0, width_angle_deg=20.0):
    return Confidence(peak_ratio, width_axial_mm, width_angle_deg, 1.0 - peak_ratio)


def test_a_longer_lobe_gives_a_longer_region_and_a_sharp_one_the_floor():
    sharp = localization_region(_confidence(width_axial_mm=2.0, width_angle_deg=1.0), circumference_mm=360.0,
                                axial_span_mm=400.0)
    long = localization_region(_confidence(width_axial_mm=180.0), circumference_mm=360.0, axial_span_mm=400.0)
    assert (sharp.axial_half_mm, sharp.circumferential_half_mm) == (AXIAL_FLOOR_MM, CIRC_FLOOR_MM)
    assert long.axial_half_mm > 4 * sharp.axial_half_mm and long.localized


def test_a_rival_peak_as_high_means_the_position_is_not_resolved():
    region = localization_region(_confidence(peak_ratio=0.99), circumference_mm=360.0, axial_span_mm=400.0)
    assert not region.localized and "competing peak" in region.reason
    assert region.axial_half_mm >= 400.0 and region.circumferential_half_mm == pytest.approx(180.0)


def test_a_lobe_along_the_whole_axis_resolves_the_angle_only():
    region = localization_region(_confidence(width_axial_mm=390.0), circumference_mm=360.0, axial_span_mm=400.0)
    assert not region.localized and "axial position" in region.reason
    assert region.axial_half_mm >= 400.0 and region.circumferential_half_mm < 20.0


def test_containment_is_a_rectangle_on_the_wall_that_wraps_round():
    region = Region(10.0, 5.0)
    assert region.contains(100.0, 359.0, 109.0, 3.0, 360.0)  # 4 mm round through 0 deg
    assert not region.contains(100.0, 359.0, 111.0, 359.0, 360.0)
    assert not region.contains(100.0, 0.0, 100.0, 6.0, 360.0)


def test_a_detected_scatterer_lies_inside_its_stated_region_and_the_json_carries_it():
    base, cur = baseline_and_scatterers([(210.0, 135.0, 0.05)], noise_rms=1e-3, seed=11)
    result = assess(cur, [base], AssessSettings())
    (defect,) = result.defects
    assert surface_distance_mm(defect.axial_mm, defect.angle_deg, 210.0, 135.0, CIRCUMFERENCE_MM) > 0
    assert defect.region.localized
    assert defect.region.contains(defect.axial_mm, defect.angle_deg, 210.0, 135.0, CIRCUMFERENCE_MM)
    out = result.as_json()["defects"][0]["region"]
    assert out["coverage"] == 0.9 and out["localized"] is True and out["axial_half_mm"] > 0
