"""Detection threshold: calibration from a defect-free campaign, false-alarm rate, probability of detection.

A campaign is the peak DI of many measurements taken in baseline condition (no defect, but
with the node's real noise and temperature drift), each imaged exactly as in service. The
threshold is either mean + k sigma of those peaks, k from the wanted false-alarm rate under a
Gaussian model, or their empirical (1 - rate) quantile. The Gaussian rule extrapolates beyond
the campaign (useful for rates below 1 / campaign size) and is only as good as the Gaussian
model of the tail; the quantile needs at least 1 / rate measurements.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import stats as sp_stats


class CalibrationError(ValueError):
    """Too few campaign measurements, or a rate outside (0, 1)."""


@dataclass(frozen=True)
class Calibration:
    """A calibrated threshold and how it was obtained."""

    threshold: float
    rule: Literal["gaussian", "quantile"]
    false_alarm_rate: float
    k_sigma: float
    n_measurements: int
    mean: float
    std: float

    def as_dict(self) -> dict:
        return {
            "threshold": self.threshold,
            "rule": self.rule,
            "false_alarm_rate": self.false_alarm_rate,
            "k_sigma": self.k_sigma,
            "n_measurements": self.n_measurements,
            "mean": self.mean,
            "std": self.std,
        }


def _peaks(peak_dis) -> np.ndarray:
    peaks = np.asarray(peak_dis, dtype=np.float64).ravel()
    if peaks.size < 2 or not np.all(np.isfinite(peaks)):
        raise CalibrationError("need at least two finite peak DIs")
    return peaks


def calibrate_threshold(
    peak_dis, *, false_alarm_rate: float = 1e-3, rule: Literal["gaussian", "quantile"] = "gaussian"
) -> Calibration:
    """Threshold from the peak DIs of a defect-free campaign for a wanted per-measurement false-alarm rate."""
    if not 0.0 < false_alarm_rate < 1.0:
        raise CalibrationError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate}")
    peaks = _peaks(peak_dis)
    mean, std = float(peaks.mean()), float(peaks.std(ddof=1))
    k = float(sp_stats.norm.isf(false_alarm_rate))
    if rule == "gaussian":
        threshold = mean + k * std
    elif rule == "quantile":
        if peaks.size * false_alarm_rate < 1.0:
            raise CalibrationError(
                f"a {false_alarm_rate:g} quantile needs at least {math.ceil(1 / false_alarm_rate)} measurements, "
                f"got {peaks.size}"
            )
        threshold = float(np.quantile(peaks, 1.0 - false_alarm_rate, method="higher"))
    else:
        raise CalibrationError(f"unknown rule {rule!r}")
    return Calibration(threshold, rule, false_alarm_rate, k, int(peaks.size), mean, std)


def false_alarm_rate(peak_dis, threshold: float) -> float:
    """Fraction of defect-free peak DIs at or above ``threshold`` (empirical)."""
    peaks = _peaks(peak_dis)
    return float(np.mean(peaks >= threshold))


def gaussian_false_alarm_rate(peak_dis, threshold: float) -> float:
    """Tail probability above ``threshold`` of a Gaussian fitted to defect-free peak DIs."""
    peaks = _peaks(peak_dis)
    return float(sp_stats.norm.sf(threshold, loc=peaks.mean(), scale=peaks.std(ddof=1)))


def probability_of_detection(defect_peak_dis, threshold: float) -> float:
    """Fraction of measurements of a defect (of one strength) whose peak DI reaches ``threshold``."""
    peaks = _peaks(defect_peak_dis)
    return float(np.mean(peaks >= threshold))


def gaussian_probability_of_detection(defect_peak_dis, threshold: float) -> float:
    """POD from a Gaussian fitted to the defect's peak DIs: P(DI >= threshold)."""
    peaks = _peaks(defect_peak_dis)
    return float(sp_stats.norm.sf(threshold, loc=peaks.mean(), scale=peaks.std(ddof=1)))


# Defaults for a node without calibration, per (method, feature). Unit-free: the multipath DI
# is in units of the baseline's direct-arrival amplitude (matched-filter statistic), the
# paper's DI divided by the direct arrival's own window energy. Measured: docs/accuracy.md.
# multipath/analytic: about twice the largest defect-free peak measured on any physics (0.0048: the
# project's FDTD, a sound 8-ring reflecting pipe 15 degC colder than its baseline; the full-wave
# dev set's noisy records 0.0046; the mock's 1000-record campaigns at +-2-3 degC 0.0040). It was
# 0.02 until 2026-12-06, set when the largest such peak was 0.0166; at 0.02 the full-wave sets'
# 15 x 5 x 1 mm notches without end echoes (DI 0.012-0.019) were missed.
DEFAULT_THRESHOLDS: dict[tuple[str, str], float] = {
    ("multipath", "analytic"): 0.01,
    ("multipath", "envelope"): 0.02,
    ("multipath", "squared"): 0.005,
    ("paper", "analytic"): 0.001,
    ("paper", "envelope"): 0.001,
    ("paper", "squared"): 0.001,
}


def default_threshold(method: str, feature: str) -> float:
    """The documented default detection threshold for a method and feature."""
    try:
        return DEFAULT_THRESHOLDS[(method, feature)]
    except KeyError as exc:
        raise CalibrationError(f"no default threshold for method {method!r} with feature {feature!r}") from exc
