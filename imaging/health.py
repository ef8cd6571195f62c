"""Transducer health: is each receiver channel's direct arrival still what the baseline recorded?

A dead or debonded receiver loses most of its direct T(0,1) arrival; a damaged cable or a
moved transducer shifts it in time. Both change that channel's whole record and would image
as "damage" if left in the map, so they are reported as sensor faults and left out instead.
A real defect changes the direct arrival of the receivers in its shadow by a few percent
only (paper, Table 3: 1-5 % for a 10 kg clamp), far inside these limits.
Temperature shifts every channel alike, so timing is judged against the median shift.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from imaging.arrivals import direct_arrival
from imaging.dimap import check_compatible
from imaging.measurement import Measurement

MIN_AMPLITUDE_RATIO = 0.5  # current / baseline direct-arrival amplitude below this: channel faulty
MAX_AMPLITUDE_RATIO = 2.0
MAX_DELAY_PERIODS = 0.25  # timing change (relative to the median channel) above a quarter period
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
    """Faulty receivers, comparing each channel's direct arrival (amplitude, time) with the baseline's."""
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
    base, cur = direct_arrival(baseline), direct_arrival(current)
    safe = np.where(base.amplitude > 0, base.amplitude, 1.0)
    ratio = np.where(base.amplitude > 0, cur.amplitude / safe, 0.0)
    shift = cur.time_s - base.time_s
    delay = shift - np.median(shift)
    period_s = 1.0 / current.excitation_hz
    faults = []
    for m in range(current.n_rx):
        kind: FaultKind
        if ratio[m] < 0.1:
            kind = "no_signal"
        elif not min_ratio <= ratio[m] <= max_ratio:
            kind = "amplitude"
        elif abs(delay[m]) > max_delay_periods * period_s:
            kind = "timing"
        else:
            continue
        faults.append(SensorFault(m, float(current.rx_angles_deg[m]), kind, float(ratio[m]), float(delay[m])))
    return faults


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
