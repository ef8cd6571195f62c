"""What the node's receiver chain does to a noise-free full-wave pair: noise, a 10-bit ADC, decimation.

As the dev set describes it (its README): Gaussian noise 40 dB below the direct arrival (an RMS
of 1 % of the baseline's direct-arrival peak, drawn afresh for each record), then an ADC of
``adc_bits`` over +-1.2 x the baseline's largest sample (the same range for both records, so a
current record that grew can clip), then optionally a plain subsample to a lower rate (the
cheapest FPGA decimation: keep every ``factor``-th sample, no anti-alias filter).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from imaging.measurement import Measurement

NOISE_BELOW_DIRECT_DB = 40.0
ADC_BITS = 10
FULL_SCALE_OVER_PEAK = 1.2
DIRECT_WINDOW_MARGIN_S = 10e-6


class AcquisitionError(ValueError):
    """Receiver-chain settings that make no sense (bits, factor, a silent baseline)."""


def direct_arrival_peak(m: Measurement) -> float:
    """Largest |sample| where the direct T(0,1) arrival lies: from the Rx ring's time of flight at the
    nominal velocity to one pulse length later, +- a margin."""
    t = m.t0_s + np.arange(m.n_samples) / m.fs_hz
    start = m.tx_rx_distance_mm * 1e-3 / m.velocity_m_s
    inside = (t >= start - DIRECT_WINDOW_MARGIN_S) & (t <= start + m.cycles / m.excitation_hz + DIRECT_WINDOW_MARGIN_S)
    if not np.any(inside):
        raise AcquisitionError("the record does not reach the direct arrival")
    peak = float(np.abs(m.traces[:, inside]).max())
    if peak <= 0:
        raise AcquisitionError("the baseline has no direct arrival to scale the noise by")
    return peak


def add_noise(m: Measurement, rms: float, rng: np.random.Generator) -> Measurement:
    return dataclasses.replace(m, traces=m.traces + rng.normal(0.0, rms, m.traces.shape))


def quantise(m: Measurement, full_scale: float, bits: int = ADC_BITS) -> Measurement:
    """Signed ``bits``-bit codes over +-full_scale, clipped, back in the record's units."""
    if not 2 <= bits <= 24:
        raise AcquisitionError(f"adc bits must be 2..24, got {bits}")
    half = 2 ** (bits - 1)
    step = full_scale / half
    codes = np.clip(np.rint(m.traces / step), -half, half - 1)
    return dataclasses.replace(m, traces=codes * step)


def subsample(m: Measurement, factor: int) -> Measurement:
    if factor < 1:
        raise AcquisitionError(f"decimation factor must be >= 1, got {factor}")
    if factor == 1:
        return m
    return dataclasses.replace(m, traces=m.traces[:, ::factor], fs_hz=m.fs_hz / factor)


def acquire_pair(baseline: Measurement, current: Measurement, rng: np.random.Generator, *, noisy: bool,
                 decimation: int = 1, noise_db: float = NOISE_BELOW_DIRECT_DB,
                 adc_bits: int = ADC_BITS) -> tuple[Measurement, Measurement]:
    """The pair as the node would deliver it; a clean pair (``noisy`` False) is only decimated."""
    if noisy:
        rms = direct_arrival_peak(baseline) * 10 ** (-noise_db / 20)
        full_scale = FULL_SCALE_OVER_PEAK * float(np.abs(baseline.traces).max())
        if not (math.isfinite(full_scale) and full_scale > 0):
            raise AcquisitionError("the baseline is silent: no ADC range")
        baseline = quantise(add_noise(baseline, rms, rng), full_scale, adc_bits)
        current = quantise(add_noise(current, rms, rng), full_scale, adc_bits)
    return subsample(baseline, decimation), subsample(current, decimation)


__all__ = ["AcquisitionError", "acquire_pair", "add_noise", "direct_arrival_peak", "quantise", "subsample"]
