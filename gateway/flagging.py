"""Damage flagging: a threshold on the DI peak with hysteresis, and threshold calibration.

States: ``ok -> suspected -> damage`` and back. The first exceedance makes a node
``suspected``; M consecutive exceedances (counting the first) make it ``damage``; a reading
below the threshold while suspected returns it to ``ok``; from ``damage`` it takes M
consecutive readings below to return to ``ok``. ``no_valid_baseline`` is entered when the
imaging abstains (no baseline matches the current conditions): monitoring is blind, not
healthy, and the counters restart when valid readings return. ``commissioning`` and
``calibrating`` come before any flagging: the node has no baseline, or no threshold yet.
"""
from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, replace

from db.models import NodeState
from gateway.config import ThresholdSettings

FLAGGING_STATES = (NodeState.OK, NodeState.SUSPECTED, NodeState.DAMAGE)


@dataclass(frozen=True)
class FlagState:
    """What the flagger remembers between measurements of one node."""

    state: NodeState = NodeState.OK
    above: int = 0  # consecutive readings above the threshold
    below: int = 0  # consecutive readings below the threshold (counted while in damage)


def step(prev: FlagState, peak_di: float | None, threshold: float, hysteresis_count: int) -> FlagState:
    """The next state after one reading. ``peak_di=None`` means the imaging abstained."""
    m = hysteresis_count
    if peak_di is None:
        return FlagState(NodeState.NO_VALID_BASELINE)
    state = prev.state if prev.state in FLAGGING_STATES else NodeState.OK
    if peak_di > threshold:
        above = prev.above + 1 if state in (NodeState.SUSPECTED, NodeState.DAMAGE) else 1
        if state == NodeState.DAMAGE or above >= m:
            return FlagState(NodeState.DAMAGE, above=above, below=0)
        return FlagState(NodeState.SUSPECTED, above=above, below=0)
    if state == NodeState.DAMAGE:
        below = prev.below + 1
        if below >= m:
            return FlagState(NodeState.OK)
        return replace(prev, state=NodeState.DAMAGE, above=0, below=below)
    return FlagState(NodeState.OK)


def restored_flag_state(readings: Sequence[tuple[float, float]], node_state: NodeState) -> FlagState:
    """The flagger's memory after a restart: the stored state, and the run of consecutive readings on
    one side of the threshold at the head of ``readings`` ((peak DI, threshold), newest first)."""
    above = below = 0
    for peak, threshold in readings:
        if peak > threshold and below == 0:
            above += 1
        elif peak <= threshold and above == 0:
            below += 1
        else:
            break
    state = node_state if node_state in FLAGGING_STATES else NodeState.OK
    return FlagState(state, above=above, below=below if state == NodeState.DAMAGE else 0)


class CalibrationError(ValueError):
    """Too few or degenerate baseline-condition readings to calibrate a threshold."""


MIN_LOG_SPREAD = 0.01  # floor on the spread of log peak DIs: 1 %, so identical readings still leave a margin


def calibrated_threshold(peaks: list[float], false_alarm_rate: float) -> float:
    """Upper prediction bound for the next baseline-condition peak DI at the given false-alarm rate.

    A peak DI is the maximum over many pixels of a noisy map: positive and right-skewed, so it
    is modelled as log-normal. With K calibration readings of unknown mean and spread, the
    one-sided prediction bound for one more reading is
    ``mean(log p) + t(1 - rate, K - 1) * sd(log p) * sqrt(1 + 1/K)`` (Student t), which is wider
    than mean + z*sigma when K is small, as it must be.
    """
    values = [float(p) for p in peaks if math.isfinite(p) and p > 0]
    if len(values) < 2:
        raise CalibrationError(f"need at least 2 positive finite DI peaks to calibrate, got {len(values)}")
    if not 0 < false_alarm_rate < 1:
        raise CalibrationError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate}")
    from scipy.stats import t as student_t

    logs = [math.log(v) for v in values]
    k = len(logs)
    mean = statistics.fmean(logs)
    spread = max(statistics.stdev(logs), MIN_LOG_SPREAD)
    bound = mean + float(student_t.isf(false_alarm_rate, k - 1)) * spread * math.sqrt(1 + 1 / k)
    return math.exp(bound)


def threshold_for(settings: ThresholdSettings, calibration_peaks: list[float], floor: float = 0.0) -> float | None:
    """The node's threshold, or None while a calibrated threshold still lacks readings.

    A calibrated threshold is raised to ``floor``: a short calibration sees the temperature of
    a few minutes only, and the compensation leaves a residual that grows with the daily swing.
    """
    if settings.mode == "absolute":
        assert settings.absolute is not None  # the settings' validator requires it in this mode
        return settings.absolute
    if len(calibration_peaks) < settings.calibration_count:
        return None
    calibrated = calibrated_threshold(calibration_peaks[: settings.calibration_count], settings.false_alarm_rate)
    return max(calibrated, floor)
