"""Threshold calibration: the calibrated threshold gives the false-alarm rate asked for; POD follows."""
import numpy as np
import pytest

from imaging.detection import (
    CalibrationError,
    calibrate_threshold,
    default_threshold,
    false_alarm_rate,
    gaussian_false_alarm_rate,
    gaussian_probability_of_detection,
    probability_of_detection,
)


@pytest.mark.parametrize("rule", ["gaussian", "quantile"])
def test_calibrated_threshold_gives_the_requested_false_alarm_rate(rule):
    rng = np.random.default_rng(0)
    campaign = rng.normal(0.01, 0.002, 5000)  # peak DIs of defect-free measurements
    cal = calibrate_threshold(campaign, false_alarm_rate=0.01, rule=rule)
    fresh = rng.normal(0.01, 0.002, 200_000)
    assert false_alarm_rate(fresh, cal.threshold) == pytest.approx(0.01, rel=0.15)
    assert gaussian_false_alarm_rate(campaign, cal.threshold) == pytest.approx(0.01, rel=0.2)
    assert cal.n_measurements == 5000 and cal.rule == rule


def test_quantile_rule_refuses_too_small_a_campaign():
    with pytest.raises(CalibrationError, match="at least 1000"):
        calibrate_threshold(np.linspace(0, 1, 100), false_alarm_rate=1e-3, rule="quantile")


def test_probability_of_detection_at_the_calibrated_threshold():
    rng = np.random.default_rng(1)
    cal = calibrate_threshold(rng.normal(0.01, 0.002, 5000), false_alarm_rate=1e-3)
    strong = rng.normal(0.03, 0.002, 4000)
    marginal = rng.normal(cal.threshold, 0.002, 4000)
    assert probability_of_detection(strong, cal.threshold) > 0.99
    assert probability_of_detection(marginal, cal.threshold) == pytest.approx(0.5, abs=0.05)
    assert gaussian_probability_of_detection(marginal, cal.threshold) == pytest.approx(0.5, abs=0.05)


def test_every_method_and_feature_has_a_default_threshold():
    for method in ("multipath", "paper"):
        for feature in ("analytic", "envelope", "squared"):
            assert default_threshold(method, feature) > 0
    with pytest.raises(CalibrationError):
        default_threshold("nope", "analytic")
