"""How bad a defect is, and how fast it is getting worse.

Severity is the defect's scattered amplitude relative to the incident direct arrival, referred
to one wavelength from the defect: the least-squares strength of a point scatterer at the
estimated position, fitted to the residual feature along every modelled path (the map's
amplitude normalisation, imaging/multipath.py). It is reflection-coefficient-like: 0 for an
intact pipe, growing with the defect's cross-section; the ring-averaged T(0,1) reflection
coefficient is about severity x wavelength / circumference for a point-like defect.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SECONDS_PER_MONTH = 30.436875 * 86400.0  # mean Gregorian month


class TrendError(ValueError):
    """Too few or malformed points to fit a trend."""


@dataclass(frozen=True)
class SeverityTrend:
    """Least-squares line through severity(t): ``rate_per_month``, value ``at_last`` (fitted) and its
    standard error (NaN with two points)."""

    rate_per_month: float
    rate_stderr_per_month: float
    at_last: float
    n_points: int

    def as_dict(self) -> dict:
        return {
            "rate_per_month": self.rate_per_month,
            "rate_stderr_per_month": self.rate_stderr_per_month,
            "at_last": self.at_last,
            "n_points": self.n_points,
        }


def severity_trend(times_s: np.ndarray, severities: np.ndarray) -> SeverityTrend:
    """Rate of change of severity per month at one location, from (time in seconds, severity) pairs."""
    t = np.asarray(times_s, dtype=np.float64)
    s = np.asarray(severities, dtype=np.float64)
    if t.shape != s.shape or t.ndim != 1:
        raise TrendError("times_s and severities must be 1-D arrays of the same length")
    if t.size < 2:
        raise TrendError("a trend needs at least two points")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(s))):
        raise TrendError("times and severities must be finite")
    months = (t - t.mean()) / SECONDS_PER_MONTH
    spread = float(np.sum(months * months))
    if spread == 0.0:
        raise TrendError("all points are at the same time")
    slope = float(np.sum(months * (s - s.mean())) / spread)
    fitted_last = float(s.mean() + slope * months[np.argmax(t)])
    if t.size > 2:
        resid = s - (s.mean() + slope * months)
        stderr = math.sqrt(float(np.sum(resid * resid)) / (t.size - 2) / spread)
    else:
        stderr = math.nan
    return SeverityTrend(slope, stderr, fitted_last, int(t.size))
