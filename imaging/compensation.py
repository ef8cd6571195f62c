"""Temperature compensation: optimal baseline selection (OBS) and baseline signal stretch (BSS).

Warming slows the T(0,1) wave (about 1e-4 per degC in steel), so every arrival of the
current record comes a factor (1 + stretch) later than in a baseline taken colder:
current(t) ~ baseline(t / (1 + stretch)), t counted from the excitation start. BSS finds that
factor by minimising the relative residual energy ||current - stretched||^2 / ||current||^2
over a bounded range (coarse grid, then a bounded scalar refinement); OBS does it for every
baseline of a library and keeps the best. When even the best leaves more than
``max_residual`` the library has no valid baseline and we abstain (``NoValidBaseline``)
rather than image against a wrong reference.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy import interpolate as sp_interpolate
from scipy import optimize as sp_optimize

from imaging.dimap import BaselineMismatch, check_compatible
from imaging.measurement import Measurement

DEFAULT_MAX_STRETCH = 0.005  # +-0.5 %: about +-50 degC of velocity change in steel
DEFAULT_MAX_RESIDUAL = 0.05  # relative residual energy above which no baseline is trusted
COARSE_STEPS = 21  # stretch grid of the first pass; a step of 0.05 % at +-0.5 %
SEARCH_DECIMATION = 4  # the search compares every 4th sample (>= 29 samples per period at 85 kHz, 10 MHz)
REFINE_XTOL = 1e-7
TIE_TOLERANCE = 0.05  # residuals within 5 % of the best count as a tie: take the smallest |stretch|


class CompensationError(ValueError):
    """An empty library or bad search settings."""


@dataclass(frozen=True)
class BaselineMatch:
    """The baseline chosen for a current record: its library ``index``, the ``stretch`` applied, the
    remaining relative ``residual`` energy, and the stretched ``baseline`` itself."""

    index: int
    stretch: float
    residual: float
    baseline: Measurement

    def as_dict(self) -> dict:
        return {"baseline_index": self.index, "stretch": self.stretch, "residual": self.residual}


@dataclass(frozen=True)
class NoValidBaseline:
    """No baseline in the library matches the current record well enough: abstain, do not image."""

    best_index: int | None
    best_residual: float
    max_residual: float
    reason: str

    def as_dict(self) -> dict:
        return {
            "baseline_index": self.best_index,
            "residual": self.best_residual,
            "max_residual": self.max_residual,
            "reason": self.reason,
        }


def _sample_times_s(m: Measurement) -> np.ndarray:
    return m.t0_s + np.arange(m.n_samples) / m.fs_hz


def _spline(m: Measurement, rows: np.ndarray | None = None) -> sp_interpolate.CubicSpline:
    traces = m.traces if rows is None else m.traces[rows]
    return sp_interpolate.CubicSpline(_sample_times_s(m), traces.astype(np.float64), axis=1)


def _evaluate(spline: sp_interpolate.CubicSpline, times_s: np.ndarray, stretch: float) -> np.ndarray:
    """Baseline at t / (1 + stretch); zero outside the recorded interval (no extrapolation)."""
    t = times_s / (1.0 + stretch)
    lo, hi = spline.x[0], spline.x[-1]
    out = spline(np.clip(t, lo, hi))
    out[:, (t < lo) | (t > hi)] = 0.0
    return out


def stretch_traces(m: Measurement, stretch: float) -> np.ndarray:
    """The traces time-stretched by (1 + stretch) about the excitation start, cubic-spline resampled."""
    return _evaluate(_spline(m), _sample_times_s(m), stretch)


def stretched(m: Measurement, stretch: float) -> Measurement:
    """A copy of ``m`` as if recorded with every arrival (1 + stretch) times later."""
    if stretch == 0.0:
        return m
    return replace(m, traces=stretch_traces(m, stretch).astype(np.float32))


def _relative_residual(reference: np.ndarray, candidate: np.ndarray) -> float:
    energy = float(np.sum(reference * reference))
    diff = reference - candidate
    return float(np.sum(diff * diff)) / energy if energy > 0 else math.inf


def best_stretch(
    baseline: Measurement,
    current: Measurement,
    *,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    rx_mask: np.ndarray | None = None,
) -> tuple[float, float]:
    """(stretch, relative residual) minimising ||current - baseline stretched||^2 / ||current||^2.

    The search is bounded to [-max_stretch, max_stretch]: a coarse grid of COARSE_STEPS, then
    Brent's bounded method inside the best grid cell (at most 60 evaluations). Receivers
    where ``rx_mask`` is False (faulty channels) are left out of the comparison.
    """
    check_compatible(baseline, current)
    rows = np.ones(current.n_rx, bool) if rx_mask is None else np.asarray(rx_mask, bool)
    if not (0 <= max_stretch < 0.1):
        raise CompensationError(f"max_stretch must be in [0, 0.1), got {max_stretch}")
    spline = _spline(baseline, rows)
    times = _sample_times_s(current)
    sub = times[::SEARCH_DECIMATION]
    target_sub = current.traces[rows, ::SEARCH_DECIMATION].astype(np.float64)

    def cost(s: float) -> float:
        return _relative_residual(target_sub, _evaluate(spline, sub, s))

    if max_stretch == 0:
        best = 0.0
    else:
        grid = np.linspace(-max_stretch, max_stretch, COARSE_STEPS)
        costs = [cost(float(s)) for s in grid]
        k = int(np.argmin(costs))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
        res = sp_optimize.minimize_scalar(
            cost, bounds=(lo, hi), method="bounded", options={"xatol": REFINE_XTOL, "maxiter": 60}
        )
        best = float(res.x) if res.fun <= costs[k] else float(grid[k])
    target = current.traces[rows].astype(np.float64)
    return best, _relative_residual(target, _evaluate(spline, times, best))


def select_baseline(
    library: Sequence[Measurement],
    current: Measurement,
    *,
    compensate: bool = True,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    max_residual: float = DEFAULT_MAX_RESIDUAL,
    rx_mask: np.ndarray | None = None,
) -> BaselineMatch | NoValidBaseline:
    """OBS (+ BSS when ``compensate``): the library entry that best explains ``current``, or abstain.

    Without compensation the entry with the smallest unstretched residual is chosen. Receivers
    where ``rx_mask`` is False are left out of the comparison. Entries
    incompatible with ``current`` (other geometry or sampling) are skipped; if none is
    compatible the result is NoValidBaseline naming the first mismatch.
    """
    if len(library) == 0:
        raise CompensationError("the baseline library is empty")
    candidates: list[tuple[float, int, float]] = []
    mismatch = None
    for i, baseline in enumerate(library):
        try:
            if compensate:
                stretch, residual = best_stretch(baseline, current, max_stretch=max_stretch, rx_mask=rx_mask)
            else:
                check_compatible(baseline, current)
                rows = np.ones(current.n_rx, bool) if rx_mask is None else np.asarray(rx_mask, bool)
                stretch = 0.0
                residual = _relative_residual(
                    current.traces[rows].astype(np.float64), baseline.traces[rows].astype(np.float64)
                )
        except BaselineMismatch as exc:
            mismatch = mismatch or str(exc)
            continue
        candidates.append((residual, i, stretch))
    if not candidates:
        return NoValidBaseline(None, math.inf, max_residual, f"no compatible baseline: {mismatch}")
    # Among near-equal matches prefer the least stretch: the closest temperature also matches
    # what a stretch cannot model (amplitude, mode shape changes with temperature).
    lowest = min(c[0] for c in candidates)
    ties = [c for c in candidates if c[0] <= lowest * (1.0 + TIE_TOLERANCE)]
    residual, index, stretch = min(ties, key=lambda c: (abs(c[2]), c[0]))
    if not residual <= max_residual:
        return NoValidBaseline(
            index, residual, max_residual,
            f"best baseline leaves {residual:.3g} of the signal energy unexplained (limit {max_residual:.3g})",
        )
    return BaselineMatch(index, stretch, residual, stretched(library[index], stretch))
