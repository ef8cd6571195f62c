"""Damage flagging: hysteresis ok -> suspected -> damage and back, and threshold calibration."""
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import t as student_t

from gateway.config import ThresholdSettings
from gateway.flagging import (
    CalibrationError,
    FlagState,
    NodeState,
    calibrated_threshold,
    step,
    threshold_for,
)


def run(readings, threshold=1.0, m=3):
    state, history = FlagState(), []
    for r in readings:
        state = step(state, r, threshold, m)
        history.append(state.state)
    return history


def test_damage_needs_m_consecutive_exceedances():
    assert run([2, 2, 2]) == [NodeState.SUSPECTED, NodeState.SUSPECTED, NodeState.DAMAGE]


def test_a_single_exceedance_is_only_suspected_and_returns_to_ok():
    assert run([2, 0.5, 2, 0.5]) == [NodeState.SUSPECTED, NodeState.OK, NodeState.SUSPECTED, NodeState.OK]


def test_damage_clears_only_after_m_consecutive_readings_below():
    h = run([2, 2, 2, 0.5, 0.5, 2, 0.5, 0.5, 0.5])
    assert h[2:] == [NodeState.DAMAGE] * 6 + [NodeState.OK]


def test_m_of_one_flags_at_once():
    assert run([2, 0.5], m=1) == [NodeState.DAMAGE, NodeState.OK]


def test_abstention_is_its_own_state_and_restarts_the_count():
    h = run([2, 2, None, 2, 2, 2])
    assert h == [
        NodeState.SUSPECTED,
        NodeState.SUSPECTED,
        NodeState.NO_VALID_BASELINE,
        NodeState.SUSPECTED,
        NodeState.SUSPECTED,
        NodeState.DAMAGE,
    ]


@given(st.lists(st.one_of(st.none(), st.floats(0, 3)), max_size=60), st.integers(1, 5))
def test_damage_is_never_flagged_without_m_exceedances_in_a_row(readings, m):
    state, run_len = FlagState(), 0
    for r in readings:
        prev = state.state
        state = step(state, r, 1.0, m)
        run_len = run_len + 1 if (r is not None and r > 1.0) else 0
        if state.state == NodeState.DAMAGE and prev != NodeState.DAMAGE:
            assert run_len >= m


def test_calibrated_threshold_is_the_log_normal_prediction_bound():
    peaks = [1.0, 1.2, 0.8, 1.1, 0.9]
    logs = np.log(peaks)
    expected = math.exp(logs.mean() + student_t.isf(1e-3, 4) * logs.std(ddof=1) * math.sqrt(1 + 1 / 5))
    assert calibrated_threshold(peaks, 1e-3) == pytest.approx(expected, rel=1e-12)


def test_few_calibration_readings_give_a_wider_bound_than_many():
    rng = np.random.default_rng(3)
    peaks = list(np.exp(rng.normal(0.0, 0.1, 200)))
    assert calibrated_threshold(peaks[:5], 1e-3) > calibrated_threshold(peaks, 1e-3)


def test_calibrated_threshold_holds_its_false_alarm_rate_on_log_normal_peaks():
    rng = np.random.default_rng(11)
    thresholds = [calibrated_threshold(list(np.exp(rng.normal(0.0, 0.2, 10))), 0.01) for _ in range(400)]
    fresh = np.exp(rng.normal(0.0, 0.2, 400))
    rate = float(np.mean(fresh > np.array(thresholds)))
    assert rate < 0.03  # nominal 1 %; a bound learnt from 10 readings must not be far above it


def test_identical_calibration_readings_still_give_a_margin():
    assert calibrated_threshold([2.0] * 5, 1e-3) > 2.0


def test_calibration_needs_two_readings():
    with pytest.raises(CalibrationError):
        calibrated_threshold([1.0, math.nan], 1e-3)


def test_calibrated_threshold_is_never_below_the_floor():
    s = ThresholdSettings(mode="calibrated", calibration_count=5)
    peaks = [1.0, 1.01, 0.99, 1.0, 1.0]
    assert threshold_for(s, peaks, floor=0.0) < 2.0
    assert threshold_for(s, peaks, floor=2.0) == 2.0
    assert threshold_for(ThresholdSettings(mode="absolute", absolute=1.5), [], floor=2.0) == 1.5


def test_fewer_than_five_calibration_readings_is_a_config_error():
    with pytest.raises(ValueError, match="calibration_count"):
        ThresholdSettings(mode="calibrated", calibration_count=3)


def test_threshold_waits_for_k_calibration_readings():
    s = ThresholdSettings(mode="calibrated", calibration_count=5)
    assert threshold_for(s, [1.0, 1.1, 0.9, 1.0]) is None
    assert threshold_for(s, [1.0, 1.1, 0.9, 1.0, 1.05]) > 1.1
    assert threshold_for(ThresholdSettings(mode="absolute", absolute=7.0), []) == 7.0
