"""A ring whose gain drifts as a whole is not a defect: the matched baseline is scaled by the receivers'
common gain where that gain explains the change, and only there.

Against an unscaled baseline a drift leaves a copy of the record that the map images as a scatterer at the
Tx ring: on the full-wave dev set's sound 16-ring pipe, 1 % less gain peaked at DI 0.025 and 5 % at 0.11,
against the default threshold then, 0.02 (2026-12-03; 0.01 since 2026-12-06). The physics here is the project's own FDTD (fullwave/).
"""
import math
from dataclasses import replace

import numpy as np
import pytest

from fullwave.defects import Notch
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.compensation import (
    DEFAULT_MAX_COMPENSATED_STRETCH,
    MIN_GAIN_EXPLAINED,
    common_gain_of,
    scaled,
    select_compatible_baseline,
)
from imaging.health import MAX_COMMON_GAIN_CHANGE
from imaging.pipeline import AssessSettings, assess
from imaging.timing import surface_distance_mm

GATEWAY = AssessSettings(max_compensated_stretch=DEFAULT_MAX_COMPENSATED_STRETCH, wall_mm=4.0)
MID_WALL_MM = math.pi * (114.6 - 4.0)
NOTCH = Notch(axial_mm=180.0, angle_deg=120.0)


def _sixteen_ring(*defects, temperature_c: float = 20.0) -> SimulationSpec:
    return SimulationSpec(pipe=PipeModel(length_mm=600.0, ends="reflecting"),
                          rings=RingLayout(tx_axial_mm=150.0, n_transducers=16, tx_rx_distance_mm=300.0),
                          excitation_hz=85e3, cell_mm=2.0, n_samples=4000, temperature_c=temperature_c,
                          defects=tuple(defects))


@pytest.fixture(scope="module")
def pipe():
    """(baseline, a later record of the same sound pipe, the same pipe with a notch), noise added."""
    rng = np.random.default_rng(7)

    def noisy(m):
        return replace(m, traces=(m.traces + rng.normal(0, 0.01 * float(np.abs(m.traces).max()), m.traces.shape))
                       .astype(np.float32))

    return (noisy(simulate(_sixteen_ring())), noisy(simulate(_sixteen_ring())),
            noisy(simulate(_sixteen_ring(NOTCH))))


@pytest.mark.parametrize("gain", [0.98, 0.95, 1.1])
def test_a_sound_pipe_whose_ring_drifted_raises_no_alarm(pipe, gain):
    baseline, sound, _ = pipe
    drifted = replace(sound, traces=sound.traces * np.float32(gain))
    unscaled = assess(drifted, [baseline], replace(GATEWAY, common_gain=False))
    assert unscaled.detected, "without the gain the drift images as a defect (the case this is for)"
    result = assess(drifted, [baseline], GATEWAY)
    assert result.valid_baseline and not result.detected
    undrifted = assess(sound, [baseline], GATEWAY).peak_di  # the record's own noise, no drift
    # The drift adds nothing but its scale: the record's own noise, in units of the unscaled baseline.
    assert result.peak_di == pytest.approx(gain * undrifted, rel=0.05)
    assert result.baseline.gain == pytest.approx(gain, rel=2e-3)
    assert result.as_json()["baseline"]["gain"] == result.baseline.gain


def test_a_notch_is_not_taken_for_a_drift(pipe):
    baseline, _, notched = pipe
    assert common_gain_of(baseline, notched) == 1.0  # its scattered arrivals are no gain's
    result = assess(notched, [baseline], GATEWAY)
    assert result.baseline.gain == 1.0 and result.detected
    best = result.defects[0]
    assert surface_distance_mm(best.axial_mm, best.angle_deg, NOTCH.axial_mm, NOTCH.angle_deg, MID_WALL_MM) < 10.0


def test_a_notch_on_a_drifted_ring_is_still_found(pipe):
    baseline, _, notched = pipe
    result = assess(replace(notched, traces=notched.traces * np.float32(0.9)), [baseline], GATEWAY)
    assert result.detected
    best = result.defects[0]
    assert surface_distance_mm(best.axial_mm, best.angle_deg, NOTCH.axial_mm, NOTCH.angle_deg, MID_WALL_MM) < 10.0


def test_a_drift_with_a_temperature_change_is_undone_after_the_stretch():
    baseline = simulate(_sixteen_ring())
    warm = simulate(_sixteen_ring(temperature_c=28.0))
    drifted = replace(warm, traces=warm.traces * np.float32(0.95))
    result = assess(drifted, [baseline], GATEWAY)
    assert result.baseline.stretch == pytest.approx(8e-4, abs=1.5e-4)
    assert result.baseline.gain == pytest.approx(0.95, rel=5e-3)
    assert not result.detected


def test_a_gain_beyond_the_bound_is_not_compensated_but_abstained_on(pipe):
    baseline, sound, _ = pipe
    assert math.log(1 / 0.7) > MAX_COMMON_GAIN_CHANGE
    result = assess(replace(sound, traces=sound.traces * np.float32(0.7)), [baseline], GATEWAY)
    assert not result.valid_baseline and "gain or coupling changed" in result.no_valid_baseline.reason


def test_the_gain_is_judged_in_band_and_must_explain_half_the_change(pipe):
    baseline, sound, _ = pipe
    assert common_gain_of(baseline, scaled(sound, 0.97)) == pytest.approx(0.97, rel=2e-3)
    # a drift buried in noise explains less than MIN_GAIN_EXPLAINED of the change: gain 1 (not compensated)
    rng = np.random.default_rng(3)
    drowned = replace(sound, traces=(sound.traces * np.float32(0.97) + rng.normal(
        0, 0.5 * float(np.abs(sound.traces).max()), sound.traces.shape)).astype(np.float32))
    assert common_gain_of(baseline, drowned) == 1.0
    assert MIN_GAIN_EXPLAINED > 0
    # the search uses it: a drifted record is matched with the gain, not with a stretch it would buy
    match = select_compatible_baseline([baseline], [0], scaled(sound, 0.95), common_gain=True)
    assert match.gain == pytest.approx(0.95, rel=2e-3) and abs(match.stretch) < 2e-5
