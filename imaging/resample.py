"""Cubic B-spline interpolation of a record's traces at any times (what baseline stretching needs).

The interpolating spline's coefficients come from one recursive prefilter per row
(scipy.ndimage.spline_filter1d, mirror boundaries); a value is 4 coefficients times the cubic
B-spline's weights, for all rows at once. At >= 100 samples per period (85 kHz at 10 MHz) it
matches a not-a-knot cubic spline to ~1e-7 of the signal except within a few samples of the
record's ends (tested). Two implementations of the same sum: a compiled numba kernel (one pass,
no temporaries) and a numpy fallback (four takes); ``Resampler`` uses the kernel when numba is
importable and PIPESENTRY_NUMBA is not "0" (imaging/jit.py); tests hold the two equal.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from imaging.jit import njit, numba_module
from imaging.measurement import Measurement


def _weights(f: np.ndarray | float) -> tuple:
    """The cubic B-spline's four weights at fractional offset ``f`` (w2 closes the partition of unity);
    arrays in numpy, one point at a time in the compiled kernel."""
    g = 1.0 - f
    f3 = f * f * f
    w0 = g * g * g / 6.0
    w3 = f3 / 6.0
    w1 = 2.0 / 3.0 - f * f + 0.5 * f3
    w2 = 1.0 - w0 - w1 - w3
    return w0, w1, w2, w3


def values_numpy(coef: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """Values [n_points, n_rows] at sample positions ``x`` [n_points] of the time-major, mirror-extended
    coefficients ``coef`` [n + 3, n_rows] (row e holds coefficient e - 1); zero outside [0, n - 1]."""
    outside = (x < 0) | (x > n - 1)
    x = np.clip(x, 0.0, n - 1)
    i = np.minimum(np.floor(x), max(n - 2, 0)).astype(np.intp)
    weights = _weights(x - i)
    # Two reused buffers (no temporary per term: these arrays are large).
    out = np.take(coef, i, axis=0)
    out *= np.where(outside, 0.0, weights[0])[:, None]
    term = np.empty_like(out)
    for shift in (1, 2, 3):
        np.take(coef, i + shift, axis=0, out=term)
        term *= np.where(outside, 0.0, weights[shift])[:, None]
        out += term
    return out


def _values_loops(coef, x, n, out):  # pragma: no cover - compiled by numba
    top = max(n - 2, 0)
    for p in range(x.shape[0]):
        xv = x[p]
        if xv < 0 or xv > n - 1:
            for r in range(coef.shape[1]):
                out[p, r] = 0.0
            continue
        i = min(math.floor(xv), top)
        w0, w1, w2, w3 = _weights(xv - i)
        for r in range(coef.shape[1]):
            out[p, r] = ((coef[i, r] * w0 + coef[i + 1, r] * w1) + coef[i + 2, r] * w2) + coef[i + 3, r] * w3


def _compile():
    numba = numba_module()
    if numba is None:
        return None
    from numba.extending import register_jitable

    register_jitable(_weights)  # the kernel calls the same weights, compiled (the function stays as it is)
    t = numba.types
    signature = t.void(t.Array(t.float64, 2, "C", readonly=True), t.Array(t.float64, 1, "C", readonly=True), t.int64,
                       t.float64[:, ::1])
    return njit(numba, [signature], _values_loops)


values_compiled = _compile()


class Resampler:
    """Cubic B-spline interpolation of traces [n_rx, n] on their uniform time grid, at any times
    (module docstring). ``rows``: only these traces."""

    def __init__(self, m: Measurement, rows: np.ndarray | None = None) -> None:
        self._fit(m.traces if rows is None else m.traces[rows], m.t0_s, m.fs_hz)

    @classmethod
    def of(cls, traces: np.ndarray, t0_s: float, fs_hz: float) -> Resampler:
        """The interpolation of ``traces`` [n_rows, n] sampled at t0_s + k / fs_hz."""
        resampler = cls.__new__(cls)
        resampler._fit(traces, t0_s, fs_hz)
        return resampler

    def _fit(self, traces: np.ndarray, t0_s: float, fs_hz: float) -> None:
        coef = ndimage.spline_filter1d(np.asarray(traces, dtype=np.float64), order=3, axis=1, mode="mirror")
        n = coef.shape[1]
        # Time-major (a value gathers 4 rows of n_rx), mirror-extended one coefficient before and
        # two after: indices -1, n, n+1 are 1, n-2, n-3.
        ext = np.concatenate([coef[:, 1:2], coef, coef[:, n - 2:n - 1], coef[:, max(n - 3, 0):max(n - 3, 0) + 1]],
                             axis=1)
        self._coef = np.ascontiguousarray(ext.T)
        self._coef.setflags(write=False)
        self.t0_s, self.fs_hz, self.n = t0_s, fs_hz, n

    def __call__(self, times_s: np.ndarray, *, compiled: bool = True) -> np.ndarray:
        """Values [n_rows, *times_s.shape]; zero outside the recorded interval (no extrapolation).
        ``compiled`` False: the numpy fallback even when the kernel is there."""
        times_s = np.asarray(times_s, dtype=np.float64)
        x = np.ascontiguousarray(((times_s - self.t0_s) * self.fs_hz).ravel())
        if compiled and values_compiled is not None and self.n >= 2:
            out = np.empty((x.size, self._coef.shape[1]))
            values_compiled(self._coef, x, self.n, out)
        else:
            out = values_numpy(self._coef, x, self.n)
        return np.moveaxis(out.reshape(times_s.shape + (self._coef.shape[1],)), -1, 0)


__all__ = ["Resampler", "values_compiled", "values_numpy"]
