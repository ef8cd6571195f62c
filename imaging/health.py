"""Transducer health: is each receiver channel still recording what the baseline recorded?

A dead or debonded receiver loses most of its signal; a damaged cable, a moved transducer or a
channel's clock shifts it in time. Both change that channel's whole record and would image as
"damage" if left in the map, so they are reported as sensor faults and left out instead.

A channel fault acts on everything the channel records: it scales or shifts the whole record,
keeping its shape. A defect changes only the arrivals that pass it: a scatterer in front of a
receiver weakens, delays or reshapes that receiver's direct arrival, while the end echoes and the
rest stay. So each receiver's whole record is compared with the baseline's (``channel_changes``:
their cross-correlation gives the shift, the rms ratio and how alike they are so aligned) and
  - no signal: rms below NO_SIGNAL_RATIO of the baseline's, or nothing of it left (likeness
    below NO_LIKENESS);
  - amplitude: the same record (likeness >= SAME_SHAPE), scaled outside [0.5, 2], or any record
    outside [0.3, 3] (RESHAPED_MIN_RATIO, RESHAPED_MAX_RATIO: no defect came near);
  - timing: the same record shifted more than a quarter period from the receivers' common shift
    (temperature moves every channel alike).

Comparing the direct arrival alone does not hold on independent physics. The paper's clamp changes
it by 1-5 % (Table 3), but on full-wave records (8 and 16 transducers) a 1 kg mass in line with a
receiver weakens it to 0.67-0.8 and moves it 0.3-0.5 period, and its scattered wave, or a sparse
ring's order-N arrival trailing the direct one, can outgrow the direct arrival's envelope peak: a
peak-picking check "moved" the arrival by a whole burst (58-68 us). That check, used until
2026-12-07, flagged receivers on 44 of 339 full-wave records with defects (dev set, own cases,
held-out draws 11-20), none faulty, and left them out of the map; the whole-record comparison
flags none of them (nor any of the 74 defect-free ones), and names every channel fault of
tests/imaging/test_receiver_health.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import fft as sfft

from imaging.arrivals import analytic_from_spectrum, direct_arrival
from imaging.dimap import check_compatible
from imaging.localize import parabolic_offset
from imaging.measurement import Measurement

MIN_AMPLITUDE_RATIO = 0.5  # current / baseline rms below this (the same record scaled): channel faulty
MAX_AMPLITUDE_RATIO = 2.0
MAX_DELAY_PERIODS = 0.25  # a shift (from the receivers' common shift) above a quarter period: timing fault
SAME_SHAPE = 0.9  # the record best aligned correlates at least this with the baseline's: scaled / shifted only
NO_LIKENESS = 0.25  # ... below this nothing of the baseline's record is left: no signal
# A whole period's shift costs a burst's correlation 1 - 0.77 (5 cycles; 10 cycles: 0.06): a peak a period from
# the common shift that beats the one beside it by less than this is not a shift.
SKIP_MARGIN = 0.05
NO_SIGNAL_RATIO = 0.1  # ... nor when the record's rms is below this fraction of the baseline's
# Whatever its shape, a record this much weaker or stronger is the channel (a debond that also reshapes the
# transducer's response, pickup): a defect on the pipe moved a receiver's rms by 0.54-1.37 on the full-wave
# sets (dev, own, held-out 11-20; the least a light mass before a 16-ring receiver, likeness 0.88 there).
RESHAPED_MIN_RATIO, RESHAPED_MAX_RATIO = 0.3, 3.0
# A change of the direct arrival's amplitude common to the receivers beyond this (|median ln ratio|,
# 0.2: 18 % weaker or 22 % stronger) is the ring's gain or coupling, not the pipe: ``common_gain_change``.
# A defect lowers T(0,1)'s transmission too (the same on every receiver): measured up to 0.106 on full-wave
# strong defects, 0.151 on the mock node's mass of strength 1 (its scattered amplitude equal to the incident).
MAX_COMMON_GAIN_CHANGE = 0.2


FaultKind = Literal["no_signal", "amplitude", "timing"]


@dataclass(frozen=True)
class SensorFault:
    """One receiver judged faulty: ``kind`` is "no_signal", "amplitude" or "timing"."""

    rx_index: int
    rx_angle_deg: float
    kind: FaultKind
    amplitude_ratio: float
    delay_s: float

    def as_dict(self) -> dict:
        return {
            "rx_index": self.rx_index,
            "rx_angle_deg": self.rx_angle_deg,
            "kind": self.kind,
            "amplitude_ratio": self.amplitude_ratio,
            "delay_s": self.delay_s,
        }


def check_receivers(
    baseline: Measurement,
    current: Measurement,
    *,
    min_ratio: float = MIN_AMPLITUDE_RATIO,
    max_ratio: float = MAX_AMPLITUDE_RATIO,
    max_delay_periods: float = MAX_DELAY_PERIODS,
) -> list[SensorFault]:
    """Faulty receivers, comparing each channel's whole record with the baseline's (module docstring)."""
    check_compatible(baseline, current)
    return receiver_faults(baseline, current, min_ratio=min_ratio, max_ratio=max_ratio,
                           max_delay_periods=max_delay_periods)


def receiver_faults(
    baseline: Measurement,
    current: Measurement,
    *,
    min_ratio: float = MIN_AMPLITUDE_RATIO,
    max_ratio: float = MAX_AMPLITUDE_RATIO,
    max_delay_periods: float = MAX_DELAY_PERIODS,
) -> list[SensorFault]:
    """``check_receivers`` of a pair already known compatible (``check_compatible``)."""
    change = channel_changes(baseline, current)
    period_s = 1.0 / current.excitation_hz
    reshaped_min, reshaped_max = min(RESHAPED_MIN_RATIO, min_ratio), max(RESHAPED_MAX_RATIO, max_ratio)
    faults = []
    for m in range(current.n_rx):
        kind: FaultKind
        same_shape = change.likeness[m] >= SAME_SHAPE
        if change.ratio[m] < NO_SIGNAL_RATIO or change.likeness[m] < NO_LIKENESS:
            kind = "no_signal"
        elif ((same_shape and not min_ratio <= change.ratio[m] <= max_ratio)
              or not reshaped_min <= change.ratio[m] <= reshaped_max):
            kind = "amplitude"
        elif same_shape and abs(change.delay_s[m]) > max_delay_periods * period_s:
            kind = "timing"
        else:
            continue
        faults.append(SensorFault(m, float(current.rx_angles_deg[m]), kind, float(change.ratio[m]),
                                  float(change.delay_s[m])))
    return faults


@dataclass(frozen=True)
class ChannelChange:
    """Per receiver, the current record against the baseline's (``channel_changes``): ``ratio`` its rms
    over the baseline's; ``delay_s`` how much later it comes than the receivers' common shift;
    ``likeness`` their correlation best aligned (1: the same record, scaled and shifted)."""

    ratio: np.ndarray
    delay_s: np.ndarray
    likeness: np.ndarray


def channel_changes(baseline: Measurement, current: Measurement) -> ChannelChange:
    """Each receiver's whole record in ``current`` against ``baseline``'s (a compatible pair).

    Cross-correlated over lags of +- two burst lengths (118 us at 85 kHz); a receiver's lag is the
    correlation's carrier peak nearest its envelope's peak, refined by a parabola. The common shift
    (temperature moves every arrival alike) is the median lag of the receivers whose record kept
    its likeness there (>= SAME_SHAPE; all when none did)."""
    traces_b, traces_c = baseline.traces, current.traces
    n = current.n_samples
    lags = min(n - 1, 2 * round(current.cycles / current.excitation_hz * current.fs_hz))
    size = sfft.next_fast_len(n + lags, real=True)  # circular correlation without wrap within +- lags
    spectrum = sfft.rfft(traces_c, size, axis=1) * np.conj(sfft.rfft(traces_b, size, axis=1))
    analytic = analytic_from_spectrum(spectrum, size)  # real part: the correlation; modulus: its envelope
    analytic = np.concatenate([analytic[:, size - lags:], analytic[:, :lags + 1]], axis=1)  # lags -lags..lags
    xcorr, envelope = analytic.real, np.abs(analytic)
    # What the two records hold where they overlap at a lag: the whole energy less that of the first or last
    # |lag| samples, which the lag moves past an end (head / tail [:, k]: the first / last k samples').
    square_b, square_c = np.square(traces_b, dtype=np.float64), np.square(traces_c, dtype=np.float64)
    energy_b, energy_c = square_b.sum(axis=1), square_c.sum(axis=1)
    none = np.zeros((current.n_rx, 1))
    head_b, head_c = (np.hstack([none, np.cumsum(sq[:, :lags], axis=1)]) for sq in (square_b, square_c))
    tail_b, tail_c = (np.hstack([none, np.cumsum(sq[:, ::-1][:, :lags], axis=1)]) for sq in (square_b, square_c))
    half_period = max(1, round(current.fs_hz / current.excitation_hz / 2))

    def carrier_peak(m: int, near: int) -> tuple[float, float]:
        """(lag in samples, correlation where the records overlap) of the carrier peak within half a
        period of index ``near``."""
        first, last = max(0, near - half_period), min(xcorr.shape[1], near + half_period + 1)
        k = first + int(np.argmax(xcorr[m, first:last]))
        offset = parabolic_offset(*xcorr[m, k - 1:k + 2]) if 0 < k < xcorr.shape[1] - 1 else 0.0
        lag = k - lags  # the current's sample lag + i against the baseline's i
        if lag >= 0:  # the baseline's first n - lag samples against the current's last
            overlap = (energy_b[m] - tail_b[m, lag]) * (energy_c[m] - head_c[m, lag])
        else:
            overlap = (energy_b[m] - head_b[m, -lag]) * (energy_c[m] - tail_c[m, -lag])
        return lag + offset, float(xcorr[m, k]) / math.sqrt(overlap) if overlap > 0 else 0.0

    best = [carrier_peak(m, int(np.argmax(envelope[m]))) for m in range(current.n_rx)]
    lag = np.array([b[0] for b in best])
    likeness = np.array([b[1] for b in best])
    alike = likeness >= SAME_SHAPE
    common = float(np.median(lag[alike] if alike.any() else lag))
    # A record nearly as alike (SKIP_MARGIN) within half a period of the common shift is shifted by that
    # carrier peak's lag: its best alignment a period away is a cycle skip (full-wave, 8 transducers,
    # absorbing ends, a 1 kg mass and +8 degC: 12.3 us at 75 kHz, 0.91 against 0.90).
    near_common = [carrier_peak(m, round(common) + lags) for m in range(current.n_rx)]
    shift = np.array([near if alike_there >= best_alike - SKIP_MARGIN else far
                      for (near, alike_there), far, best_alike in zip(near_common, lag, likeness, strict=True)])
    ratio = np.sqrt(np.divide(energy_c, energy_b, out=np.zeros(current.n_rx), where=energy_b > 0))
    return ChannelChange(ratio, (shift - common) / current.fs_hz, likeness)


def common_gain_change(baseline: Measurement, current: Measurement, mask: np.ndarray | None = None) -> float:
    """ln(current / baseline) of the direct arrival's amplitude common to the receivers: the median over
    the receivers ``mask`` keeps (all when None), for a pair known compatible.

    A ring whose gain or coupling changed as a whole (ageing bond, a replaced preamplifier) moves
    every receiver alike; a defect moves those in its shadow, some up, some down. Measured on the
    full-wave dev and own sets (2026-12-03, bench/bench_reference_check.py): a near-rigid or light mass
    moves single receivers by -0.33..+0.17 but the median by 0.106 at most; a 25 % gain change gives
    0.24-0.30 on its own, 0.18-0.30 beside a strong defect (whose transmission loss offsets part of it)."""
    base, cur = direct_arrival(baseline), direct_arrival(current)
    keep = receiver_rows(current.n_rx, mask) & (base.amplitude > 0) & (cur.amplitude > 0)
    if not keep.any():
        return 0.0
    return float(np.median(np.log(cur.amplitude[keep] / base.amplitude[keep])))


def receiver_rows(n_rx: int, rx_mask: np.ndarray | None) -> np.ndarray:
    """Boolean [n_rx]: the receivers ``rx_mask`` keeps (all when None)."""
    return np.ones(n_rx, bool) if rx_mask is None else np.asarray(rx_mask, bool)


def healthy_mask(n_rx: int, faults: list[SensorFault]) -> np.ndarray:
    """Boolean [n_rx]: True for the receivers not listed in ``faults``."""
    mask = np.ones(n_rx, bool)
    for fault in faults:
        mask[fault.rx_index] = False
    return mask
