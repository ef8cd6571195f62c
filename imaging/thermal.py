"""A record as the same pipe would give it warmer or colder: the medium's response stretched, the burst not.

A change of temperature scales every wave speed of the wall by one factor (about -1e-4 per degC
in steel), so the medium's impulse response g(t) becomes g(t / (1 + s)) with s the *stretch*
(t from the excitation's start). The node's excitation burst x(t) stays what it was. The record
b = g * x therefore becomes (g stretched) * x, not b stretched: stretching the whole record also
stretches the burst, lowering its carrier by s f0 and lengthening it. That leaves a residual
growing as s^2 that a plain stretch cannot remove, and it biases the plain stretch that best
matches a warm record low (project FDTD, 600 mm sound pipe, +16 degC: the best plain stretch is
0.76-0.89 of the true one and leaves 2.5e-5 to 1.1e-4 of the record's energy; this model at the
true stretch 1.8e-6 to 1.9e-5: bench/bench_thermal.py).

With k_s the filter that turns the burst x(t) into x((1 + s) t), the warm record is (b * k_s)
stretched by (1 + s), up to a gain 1 / (1 + s): stretching g * x_s gives g stretched * x. To
first order in s (what the second order leaves, measured on a unit burst: 5.7e-4 of its amplitude
at s = 0.15 %, 2.5e-3 at 0.4 %, tests/imaging/test_thermal.py), b * k_s = b + s b', where b' is b
filtered by k' = d k_s / ds at 0, the filter that turns x(t) into t x'(t) (x' its time derivative). k' is formed in the burst's band (a regularised
spectral ratio) and is zero outside it, so out-of-band noise is stretched as before, never
amplified. Pure functions on arrays; the stretch is applied by cubic B-spline resampling
(imaging/resample.py).
"""
from __future__ import annotations

import functools
import math

import numpy as np
from scipy import fft as sp_fft

from imaging.arrivals import hann_burst
from imaging.measurement import Measurement
from imaging.resample import Resampler

BAND_FLOOR = 1e-2  # k' is formed where the burst's spectrum exceeds ~1 % of its peak (Wiener ratio; 1e-3 and 1e-4
# leave 5-15x more of an 8-ring's +16 degC record, measured on the project FDTD)


def burst_time_derivative(fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """t x'(t) of the excitation burst x (``hann_burst``) on the same samples, t from its start: what
    d/ds x((1 + s) t) is at s = 0."""
    burst = hann_burst(fs_hz, excitation_hz, cycles)
    t = np.arange(burst.size) / fs_hz
    omega = 2.0 * math.pi * excitation_hz
    envelope = 0.5 * (1.0 - np.cos(omega * t / cycles))
    envelope_rate = 0.5 * omega / cycles * np.sin(omega * t / cycles)
    return t * (envelope_rate * np.sin(omega * t) + envelope * omega * np.cos(omega * t))


@functools.lru_cache(maxsize=16)
def _slope_filter(fs_hz: float, excitation_hz: float, cycles: int, n: int) -> tuple[int, np.ndarray]:
    """(FFT length for ``n`` samples, the spectrum of k' at that length), per acquisition setup."""
    burst = hann_burst(fs_hz, excitation_hz, cycles)
    n_fft = sp_fft.next_fast_len(n + 2 * burst.size, real=True)
    spectrum = sp_fft.rfft(burst, n_fft)
    target = sp_fft.rfft(burst_time_derivative(fs_hz, excitation_hz, cycles), n_fft)
    floor = (BAND_FLOOR * np.abs(spectrum).max()) ** 2
    response = target * np.conj(spectrum) / (np.abs(spectrum) ** 2 + floor)
    response.flags.writeable = False
    return n_fft, response


def slope_traces(traces: np.ndarray, m: Measurement) -> np.ndarray:
    """b' of ``traces`` [n_rows, n] (float64) recorded with ``m``'s burst and sampling: d/ds of b * k_s at s = 0."""
    n = traces.shape[-1]
    n_fft, response = _slope_filter(m.fs_hz, m.excitation_hz, m.cycles, n)
    spectrum = sp_fft.rfft(np.asarray(traces, dtype=np.float64), n_fft, axis=-1)
    return sp_fft.irfft(spectrum * response, n_fft, axis=-1)[..., :n]


def recorded(at_s: np.ndarray, m: Measurement) -> np.ndarray:
    """Where ``m`` has data at the times ``at_s`` a stretched record reads it at (t / (1 + stretch)):
    a colder pipe's record ends on what arrived after the baseline's end, a warmer one's may begin
    before the baseline's start; there a stretched baseline is zero and means nothing."""
    at_s = np.asarray(at_s, dtype=np.float64)
    return (at_s >= m.t0_s) & (at_s <= m.t0_s + (m.n_samples - 1) / m.fs_hz)


class ThermalStretch:
    """``m``'s traces as the same pipe would record them with every wave (1 + stretch) slower, at any
    times: values [n_rx, *times.shape]; zero outside the recorded interval. ``stretch`` is a number
    or an array broadcasting against ``times``."""

    def __init__(self, m: Measurement) -> None:
        traces = m.traces.astype(np.float64)
        self.n_rows = traces.shape[0]
        self._resampler = Resampler.of(np.concatenate([traces, slope_traces(traces, m)]), m.t0_s, m.fs_hz)

    def __call__(self, times_s: np.ndarray, stretch: float | np.ndarray) -> np.ndarray:
        stretch = np.asarray(stretch, dtype=np.float64)
        values = self._resampler(np.asarray(times_s, dtype=np.float64) / (1.0 + stretch))
        return values[:self.n_rows] + stretch * values[self.n_rows:]


__all__ = ["BAND_FLOOR", "ThermalStretch", "burst_time_derivative", "recorded", "slope_traces"]
