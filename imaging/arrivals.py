"""The known excitation burst, matched filtering, and what a trace's direct arrival looks like.

Pure functions on arrays. Times are seconds after the excitation starts; a trace's sample k
is at ``t0_s + k / fs_hz``. An arrival "at sample k" means the burst *starts* at sample k
(the convention of Algorithm 1's window start).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import fft as sp_fft

from imaging.measurement import Measurement
from imaging.timing import MM_PER_M


def hann_burst(fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """The paper's excitation 0.5 (1 - cos(2 pi f t / n)) sin(2 pi f t), 0 <= t <= n/f, sampled at fs."""
    n = max(2, math.floor(cycles / excitation_hz * fs_hz) + 1)
    t = np.arange(n) / fs_hz
    phase = 2.0 * math.pi * excitation_hz * t
    return 0.5 * (1.0 - np.cos(phase / cycles)) * np.sin(phase)


def matched_filter(traces: np.ndarray, burst: np.ndarray, *, axis: int = -1) -> np.ndarray:
    """Cross-correlation with the burst, aligned so an arrival starting at sample k peaks at k.

    out[k] = sum_j x[k + j] * burst[j], with x = 0 outside the record; same length as x.
    """
    x = np.moveaxis(np.asarray(traces, dtype=np.float64), axis, -1)
    n, p = x.shape[-1], burst.size
    n_fft = sp_fft.next_fast_len(n + p, real=True)
    spec = sp_fft.rfft(x, n_fft, axis=-1) * np.conj(sp_fft.rfft(burst, n_fft))
    out = sp_fft.irfft(spec, n_fft, axis=-1)[..., :n]
    return np.moveaxis(out, -1, axis)


def analytic_signal(x: np.ndarray, *, axis: int = -1) -> np.ndarray:
    """x + i H{x} along ``axis``: scipy.signal.hilbert's result (its test oracle) from a real FFT.

    The one-sided spectrum (DC and Nyquist once, positive frequencies twice) is the real FFT's
    output, so the forward transform is real: about a quarter less work than hilbert's complex one.
    """
    x = np.moveaxis(np.asarray(x, dtype=np.float64), axis, -1)
    n = x.shape[-1]
    return np.moveaxis(analytic_from_spectrum(sp_fft.rfft(x, axis=-1), n), -1, axis)


def analytic_from_spectrum(spec: np.ndarray, n_fft: int) -> np.ndarray:
    """The analytic signal (n_fft samples along the last axis) of the real signal whose real FFT over
    n_fft samples is ``spec``: DC and Nyquist once, positive frequencies twice, negative ones dropped,
    in one inverse (complex) transform. ``spec`` is doubled in place."""
    spec[..., 1:(n_fft + 1) // 2] *= 2.0
    return sp_fft.ifft(spec, n_fft, axis=-1, overwrite_x=True)


def analytic_matched(traces: np.ndarray, burst: np.ndarray) -> np.ndarray:
    """The analytic signal of the burst cross-correlation along the last axis, in one FFT round trip.

    ``matched_filter`` then ``analytic_signal`` take four transforms; here the correlation's
    one-sided spectrum goes straight to the inverse (complex) transform over the zero-padded
    length, and the first n samples are kept. The Hilbert transform is then taken over the padded
    correlation rather than the correlation cut to n samples, so the two differ only within about
    a burst of the record's ends (tested), where the cut one wraps the record's end onto its start.
    """
    x = np.asarray(traces, dtype=np.float64)
    n, p = x.shape[-1], burst.size
    n_fft = sp_fft.next_fast_len(n + p, real=True)
    spec = sp_fft.rfft(x, n_fft, axis=-1) * np.conj(sp_fft.rfft(burst, n_fft))
    return analytic_from_spectrum(spec, n_fft)[..., :n]


@lru_cache(maxsize=8)
def analytic_noise_correlation(fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """Re of the correlation, normalised to 1 at lag 0, of ``analytic_matched``'s output for white noise, at lags
    0, 1, ... samples (zero beyond: the burst's autocorrelation is two bursts long). Read-only.

    Two samples of the matched feature ``d`` apart share noise in this proportion; a statistic adding
    several nearby samples of one receiver has variance sum_ab w_a w_b r(|k_a - k_b|), not sum_a w_a^2.
    """
    out = np.ascontiguousarray(analytic_noise_covariance(fs_hz, excitation_hz, cycles).real)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=16)
def analytic_noise_covariance(fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """C(d) = E[A(k) conj A(k + d)] / E|A|^2 of ``analytic_matched``'s output A for white noise, at lags
    d = 0, 1, ... samples (complex; C(-d) = conj C(d); zero beyond). Read-only.

    Two weighted sums of A over different sample sets, b_g = sum_a w_a A(k_a) and b_h likewise,
    have covariance E[b_g conj b_h] = sigma^2 sum_ab w_a w_b C(k_b - k_a): the cross-Gram of the
    map's coherence groups (imaging/multipath.py). Its real part is ``analytic_noise_correlation``.
    """
    burst = hann_burst(fs_hz, excitation_hz, cycles)
    size = burst.size
    impulse = np.zeros(4 * size)
    impulse[2 * size] = 1.0
    response = analytic_matched(impulse, burst)
    corr = np.array([np.vdot(response[:response.size - d], response[d:]) for d in range(2 * size)])
    out = np.ascontiguousarray(np.conj(corr / corr[0]))
    out.setflags(write=False)
    return out


def envelope(x: np.ndarray, *, axis: int = -1) -> np.ndarray:
    """Hilbert envelope |x + i H{x}| along ``axis``."""
    return np.abs(analytic_signal(x, axis=axis))


def matched_envelope(traces: np.ndarray, fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """Envelope of the matched-filtered traces [n_rx, n]: peaks where a burst starts, amplitude-linear."""
    return envelope(matched_filter(traces, hann_burst(fs_hz, excitation_hz, cycles)))


def burst_autocorrelation_peak(fs_hz: float, excitation_hz: float, cycles: int) -> float:
    """Matched-filter envelope peak of a unit-amplitude burst: divides envelopes into trace units."""
    b = hann_burst(fs_hz, excitation_hz, cycles)
    return float(np.sum(b * b))


@dataclass(frozen=True)
class DirectArrival:
    """Per receiver: the direct T(0,1) arrival's matched-envelope peak (trace units) and its start time."""

    amplitude: np.ndarray
    time_s: np.ndarray


def direct_arrival(m: Measurement, *, search_s: float | None = None) -> DirectArrival:
    """Measure each receiver's direct arrival near its predicted time tx_rx_distance / velocity.

    Searches +- ``search_s`` (default: one burst length) around the prediction, refines the peak
    by a parabola, and returns amplitude in trace units (burst-amplitude equivalent).
    With the default search the result is memoised by the record's content (``_summary``).
    """
    if search_s is None:
        return _summary(m)[0]
    return _direct_arrival(m, matched_envelope(m.traces, m.fs_hz, m.excitation_hz, m.cycles), search_s)


def _direct_arrival(m: Measurement, env: np.ndarray, search_s: float | None) -> DirectArrival:
    scale = burst_autocorrelation_peak(m.fs_hz, m.excitation_hz, m.cycles)
    predicted_s = m.tx_rx_distance_mm / (m.velocity_m_s * MM_PER_M)
    half_s = search_s if search_s is not None else m.cycles / m.excitation_hz
    lo = int(np.clip(math.floor((predicted_s - half_s - m.t0_s) * m.fs_hz), 0, m.n_samples - 1))
    hi = int(np.clip(math.ceil((predicted_s + half_s - m.t0_s) * m.fs_hz) + 1, lo + 1, m.n_samples))
    seg = env[:, lo:hi]
    k = np.argmax(seg, axis=1)
    rows = np.arange(seg.shape[0])
    peak = seg[rows, k]
    left = seg[rows, np.maximum(k - 1, 0)]
    right = seg[rows, np.minimum(k + 1, seg.shape[1] - 1)]
    curv = left - 2 * peak + right
    safe = np.where(curv < 0, curv, -1.0)
    offset = np.where(curv < 0, np.clip(0.5 * (left - right) / safe, -0.5, 0.5), 0.0)
    time_s = m.t0_s + (lo + k + offset) / m.fs_hz
    amplitude = peak / scale
    amplitude.setflags(write=False)
    time_s.setflags(write=False)
    return DirectArrival(amplitude, time_s)


def _summary(m: Measurement) -> tuple[DirectArrival, np.ndarray]:
    """(direct arrival, median matched envelope over receivers) of a record, derived once per record.

    A node's baselines are analysed again with every measurement: the result is kept with the
    record (``Measurement.derived``), not in a module-wide cache, so threads imaging different
    nodes share nothing. The key is a digest of the traces plus every field the result depends
    on, so traces changed in place are analysed again and nothing stale is returned.
    """
    key = (*m.traces_digest(), m.fs_hz, m.t0_s, m.tx_rx_distance_mm, m.velocity_m_s, m.excitation_hz, m.cycles)

    def compute() -> tuple[DirectArrival, np.ndarray]:
        env = matched_envelope(m.traces, m.fs_hz, m.excitation_hz, m.cycles)
        median = np.median(env, axis=0)
        median.setflags(write=False)
        return _direct_arrival(m, env, None), median

    return m.derived("arrival_summary", key, compute)


def reference_amplitude(m: Measurement) -> float:
    """The direct arrival's typical amplitude (median over receivers), the unit of every normalised DI."""
    amp = float(np.median(direct_arrival(m).amplitude))
    return amp if amp > 0 else 1.0


def end_reflection_coefficients(m: Measurement) -> tuple[float, float]:
    """(near, far) pipe-end T(0,1) reflection coefficients estimated from a defect-free trace.

    The Tx ring's wave reflected at the near end reaches the Rx ring after 2 tx_axial + D, at
    the far end after 2 (L - tx_axial) - D. The matched envelope there, relative to the direct
    arrival, is the coefficient. When the two arrivals overlap (within one burst length) their
    sum is measured and split evenly; an end whose echo lies outside the record counts as 1.0.
    Unknown pipe geometry (None fields): (0, 0), the end paths are not modelled.
    """
    if m.pipe_length_mm is None or m.tx_axial_mm is None:
        return 0.0, 0.0
    env = _summary(m)[1]
    direct = reference_amplitude(m) * burst_autocorrelation_peak(m.fs_hz, m.excitation_hz, m.cycles)
    c_mm_s = m.velocity_m_s * MM_PER_M
    d = m.tx_rx_distance_mm
    near_path = 2.0 * m.tx_axial_mm + d
    far_path = 2.0 * (m.pipe_length_mm - m.tx_axial_mm) - d
    burst_mm = m.cycles / m.excitation_hz * c_mm_s

    def measured(path_mm: float) -> float | None:
        k = round((path_mm / c_mm_s - m.t0_s) * m.fs_hz)
        half = round(0.25 * m.cycles / m.excitation_hz * m.fs_hz)
        if k - half < 0 or k + half >= m.n_samples:
            return None
        return float(np.max(env[k - half : k + half + 1]) / direct)

    if abs(near_path - far_path) < burst_mm:
        both = measured(0.5 * (near_path + far_path))
        value = 1.0 if both is None else min(both / 2.0, 1.0)
        return value, value
    near, far = measured(near_path), measured(far_path)
    return (1.0 if near is None else min(near, 1.0)), (1.0 if far is None else min(far, 1.0))
