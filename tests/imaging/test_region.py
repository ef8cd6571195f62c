"""The 90 % localization region: as wide as the map's main lobe says, and an honest flag when it says nothing."""
import itertools
import math

import numpy as np
import pytest

from imaging.localize import Confidence
from imaging.paths import PathModel
from imaging.pipeline import AssessSettings, assess
from imaging.region import (
    AXIAL_FLOOR_MM,
    CIRC_FLOOR_MM,
    RECEIVER_LEAN,
    RECEIVER_LEAN_WITH_ENDS,
    Region,
    localization_region,
    receiver_lean,
    receiver_lean_mm,
)
from imaging.timing import surface_distance_mm
from tests.support.synthetic import C_M_S, CIRCUMFERENCE_MM, baseline_and_scatterers


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


@pytest.mark.parametrize("axial_mm, angle_deg", [(250.0, 200.0), (320.0, 100.0)])
@pytest.mark.parametrize("echo_placed", [False, True])
def test_a_scatterers_forward_phase_lag_reads_as_an_axial_move_on_the_map_that_the_echo_fit_undoes(
        axial_mm, angle_deg, echo_placed, monkeypatch):
    # Without end echoes, moving a scatterer by dz lengthens its path to every receiver by
    # dz (1 - cos psi); an echo whose phase lags by b (1 - cos psi), as a notch's does (b ~ 2.4 rad
    # on the full-wave dev set, docs/accuracy.md), is therefore, to the map's isotropic point, the
    # echo of a point b / k further on: the map's peak moves by about that (measured: 0.8-1.0 b / k
    # here), the angle does not, and the stated region, as wide as the map's axial lobe, still holds
    # the truth. The echo fit that places such a defect (imaging/multidefect.py ``echo_placed``) lets
    # each path's amplitude turn with the receiver's bearing, which takes up most of the lag: the
    # estimate moves by a quarter of that at most (measured: 0.13-0.23 b / k).
    from imaging import multidefect

    if not echo_placed:  # the map's peak itself, as every plane-wave defect was reported until 2026-12-06
        monkeypatch.setattr(multidefect, "echo_placed", lambda model, di: bool(model.elements))
    wavenumber = 2 * math.pi * 85e3 / (C_M_S * 1000.0)  # rad / mm
    lag = 2.4
    estimates = {}
    for b in (-lag, 0.0, lag):
        base, cur = baseline_and_scatterers([(axial_mm, angle_deg, 0.05)], noise_rms=5e-4, seed=2, forward_lag_rad=b)
        (defect,) = assess(cur, [base], AssessSettings()).defects
        assert defect.region.localized
        assert defect.region.contains(defect.axial_mm, defect.angle_deg, axial_mm, angle_deg, CIRCUMFERENCE_MM)
        estimates[b] = defect
    for b in (-lag, lag):
        shift = math.copysign(1.0, b) * (estimates[b].axial_mm - estimates[0.0].axial_mm)
        if echo_placed:
            assert abs(shift) < 0.25 * abs(b) / wavenumber
        else:
            assert 0.6 * abs(b) / wavenumber < shift < 1.2 * abs(b) / wavenumber
        assert abs(estimates[b].angle_deg - estimates[0.0].angle_deg) < 2.0


def test_a_region_widened_to_hold_a_second_estimate_keeps_the_floors_margin_round_it():
    region = Region(18.0, 9.0)
    assert region.holding(-4.0, 2.0) == region  # already inside with its margin: unchanged
    wider = region.holding(-20.0, 7.5)
    assert wider.axial_half_mm == 20.0 + AXIAL_FLOOR_MM and wider.circumferential_half_mm == 7.5 + CIRC_FLOOR_MM
    assert wider.contains(100.0, 90.0, 80.0, 90.0, 360.0) and not region.contains(100.0, 90.0, 80.0, 90.0, 360.0)
    assert Region(400.0, 180.0, False, "not resolved").holding(30.0, 10.0).localized is False


EIGHT_RX = np.arange(8) * 45.0


def test_a_sparse_rings_estimate_on_a_receivers_line_may_have_leant_from_most_of_the_half_pitch():
    on_the_line = receiver_lean_mm(90.0, EIGHT_RX, 360.0)
    assert on_the_line == pytest.approx(CIRC_FLOOR_MM + RECEIVER_LEAN * 22.5)
    assert receiver_lean_mm(112.5, EIGHT_RX, 360.0) == pytest.approx(CIRC_FLOOR_MM)  # midway: where it looks
    between = [receiver_lean_mm(a, EIGHT_RX, 360.0) for a in np.arange(90.0, 112.6, 2.5)]
    assert all(b > c for b, c in itertools.pairwise(between))  # narrower the further from the line
    assert receiver_lean_mm(1.0, EIGHT_RX, 360.0) == pytest.approx(receiver_lean_mm(359.0, EIGHT_RX, 360.0))
    assert receiver_lean_mm(90.0, EIGHT_RX, 720.0) - CIRC_FLOOR_MM == pytest.approx(2 * (on_the_line - CIRC_FLOOR_MM))


def test_a_receiver_left_out_doubles_the_gap_its_neighbours_lean_across():
    without_90 = EIGHT_RX[EIGHT_RX != 90.0]
    assert receiver_lean_mm(90.0, without_90, 360.0) == pytest.approx(CIRC_FLOOR_MM)  # now the middle of a gap
    assert receiver_lean_mm(60.0, without_90, 360.0) > receiver_lean_mm(60.0, EIGHT_RX, 360.0) + 10.0
    with pytest.raises(ValueError, match="no receiver"):
        receiver_lean_mm(0.0, [], 360.0)


def test_a_region_held_to_a_lean_grows_round_the_pipe_only_and_never_past_half_of_it():
    region = Region(18.0, 9.0)
    assert region.round_at_least(5.0, 360.0) == region
    assert region.round_at_least(19.5, 360.0) == Region(18.0, 19.5)
    assert region.round_at_least(400.0, 360.0).circumferential_half_mm == 180.0


@pytest.mark.parametrize(("tx_arcs_mm", "ends", "lean"), [
    ((0.0, 45.0), (0.1, 0.1), RECEIVER_LEAN),  # a sparse ring's fit of absorbing ends: the direct paths alone
    ((0.0, 45.0), None, RECEIVER_LEAN),  # ends not modelled
    ((0.0, 45.0), (0.55, 0.1), RECEIVER_LEAN_WITH_ENDS),  # one free end echoes back: its paths cross the direct ones
    ((), (0.1, 0.1), 0.0),  # a dense ring's plane wave: its map resolves the angle
])
def test_a_sparse_rings_defect_leans_to_a_receivers_line_and_less_with_end_echoes(tx_arcs_mm, ends, lean):
    geometry = {} if ends is None else {"near_end_mm": -100.0, "far_end_mm": 500.0,
                                        "near_reflection": ends[0], "far_reflection": ends[1]}
    assert receiver_lean(PathModel(400.0, 360.0, 42.0, tx_arcs_mm=tx_arcs_mm, **geometry)) == lean
    assert RECEIVER_LEAN_WITH_ENDS < RECEIVER_LEAN
    with_ends = receiver_lean_mm(90.0, EIGHT_RX, 360.0, RECEIVER_LEAN_WITH_ENDS)
    assert CIRC_FLOOR_MM < with_ends < receiver_lean_mm(90.0, EIGHT_RX, 360.0)
