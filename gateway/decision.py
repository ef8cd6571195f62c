"""The decision of one cycle (pure): from what storage knew about the node and what the imaging saw,
the verdict — the node's next state, the alerts to raise, whether the record grows the baseline
library, and what is stored as the verdict.

No node, no database, no clock: everything comes in as arguments, so each rule is tested
alone (tests/gateway/test_decision.py). gateway/worker.py reads the inputs, stores the verdict
in one transaction and logs it.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime

from alerts.alarms import AlarmChange, BaselineSet, NodeAlarms, alarm_change, alarm_events
from alerts.config import AlertingSettings
from alerts.sensor_faults import SensorFaultChange, SensorFaultHistory, sensor_fault_change, sensor_fault_events
from db.models import MeasurementKind, NodeState
from db.records import DetectionInput, EventInput, StateChangeInput
from gateway.assessment import detection_input, joins_library
from gateway.config import NodeSettings
from gateway.flagging import FlagState, step
from gateway.record_settings import RecordSettings, comparable
from imaging.measurement import Measurement
from imaging.pipeline import Assessment

COMMISSIONING_BASELINE = "commissioning: first measurement"  # why the first record becomes the active baseline


@dataclass(frozen=True)
class NodeHistory:
    """What storage says about the node before a cycle."""

    state: NodeState
    active_baseline_id: int | None  # the measurement the node's maps are computed against
    baseline_set_at: datetime | None  # when that baseline became active
    n_baselines: int  # measurements stored as baselines (commissioning and library)
    baseline: BaselineSet | None = None  # the active baseline's record (who set it and why): ends by re-baseline name it


def is_commissioning(settings: NodeSettings, history: NodeHistory) -> bool:
    """A node without an active baseline, or with fewer baselines than it commissions with, takes baselines."""
    return history.active_baseline_id is None or history.n_baselines < settings.commissioning_count


@dataclass(frozen=True)
class MonitoringInputs:
    """What a monitor verdict depends on besides the assessment, read from storage before the cycle."""

    flag: FlagState  # the flagger's memory
    threshold: float | None  # None while a calibrated threshold still lacks readings
    library_ids: Sequence[int]  # measurement ids of the baseline library, in the order the imaging saw it
    library: Sequence[Measurement]  # ... and the baselines themselves
    sensor_faults: SensorFaultHistory
    alarms: NodeAlarms = field(default_factory=NodeAlarms)  # the node's open alarms (alerts.alarms.open_alarms)


def comparable_inputs(
    inputs: MonitoringInputs, library_settings: Sequence[RecordSettings], record: RecordSettings
) -> tuple[MonitoringInputs, str | None]:
    """The inputs with the library cut to the baselines taken with the record's own settings, and,
    when none is, why: a record is never imaged against a baseline of other settings (a reboot
    that brought back power-up settings, a node that clamped them, a changed configuration).
    The active baseline keeps its place first when it qualifies."""
    keep, reason = comparable(record, library_settings)
    return replace(inputs, library_ids=[inputs.library_ids[i] for i in keep],
                   library=[inputs.library[i] for i in keep]), reason


@dataclass(frozen=True)
class Verdict:
    """What one measurement changes: its record's kind, the node's state, the alerts it raises."""

    kind: MeasurementKind  # BASELINE for commissioning records and records that join the library
    state: NodeState  # the node's state after the measurement
    flag: FlagState  # the flagger's memory after it
    state_change: StateChangeInput | None = None
    detection: DetectionInput | None = None  # the verdict stored with a monitor measurement
    activate_baseline: str | None = None  # the reason, when the record becomes the node's active baseline
    joins_library: bool = False  # a monitor record kept as another baseline (the library learns a temperature)
    sensor_faults: SensorFaultChange = field(default_factory=SensorFaultChange)
    alarms: AlarmChange = field(default_factory=AlarmChange)  # the damage/blind alarms raised and ended
    open_alarms: NodeAlarms = field(default_factory=NodeAlarms)  # those open before (an escalation keeps its alarm's id)

    def events(
        self, alerting: AlertingSettings, *, node_id: str, measurement_id: int, now: datetime | None = None
    ) -> list[EventInput]:
        """The outbox events of this verdict once its measurement is stored as ``measurement_id``.

        A commissioning record raises none: its state changes are the node being set up.
        """
        detection = self.detection
        if detection is None:
            return []
        before = self.state if self.state_change is None else self.state_change.from_state
        events = alarm_events(
            alerting, self.alarms, self.open_alarms, node_id=node_id, from_state=before.value,
            to_state=self.state.value, measurement_id=measurement_id, peak_di=detection.peak_di,
            threshold=detection.threshold, axial_mm=detection.axial_mm, angle_deg=detection.angle_deg,
            reason=detection.abstain_reason, occurred_at=now,
            region=(detection.defects[0].get("region") if detection.defects else None),
        )
        events += sensor_fault_events(
            alerting, self.sensor_faults, node_id=node_id, measurement_id=measurement_id, state=self.state.value, now=now
        )
        return events


def _change(before: NodeState, after: NodeState) -> StateChangeInput | None:
    return None if after == before else StateChangeInput(before, after)


def decide_commissioning(settings: NodeSettings, history: NodeHistory) -> Verdict:
    """A commissioning measurement is a baseline; the first becomes the active one. After the last the
    node calibrates its threshold (mode calibrated) or monitors at once (mode absolute)."""
    done = history.n_baselines + 1 >= settings.commissioning_count
    after = NodeState.CALIBRATING if settings.threshold.mode == "calibrated" else NodeState.OK
    state = after if done else NodeState.COMMISSIONING
    return Verdict(
        kind=MeasurementKind.BASELINE,
        state=state,
        flag=FlagState(),
        state_change=_change(history.state, state),
        activate_baseline=COMMISSIONING_BASELINE if history.active_baseline_id is None else None,
    )


def decide_monitoring(
    settings: NodeSettings,
    history: NodeHistory,
    inputs: MonitoringInputs,
    assessment: Assessment,
    *,
    temperature_c: float | None,
    now: datetime,
) -> Verdict:
    """The verdict on a monitor measurement.

    An abstaining imaging makes the node ``no_valid_baseline``; without a threshold yet it is
    ``calibrating``; otherwise the flagger's hysteresis decides (gateway/flagging.py). A
    clearly healthy record at a new temperature joins the baseline library (``joins_library``).
    The node's damage and blind alarms follow the new state (``alerts.alarms.alarm_change``): an
    open alarm the state no longer wants ends — by re-baseline when the active baseline was set
    after it was raised (so damage -> calibrating after a repair ends the damage alarm), else by
    recovery — and a wanted one that is not open is raised.
    """
    m = settings.threshold.hysteresis_count
    threshold = inputs.threshold
    if not assessment.valid_baseline:
        flag = step(inputs.flag, None, math.inf, m)
    elif threshold is None:
        flag = FlagState(NodeState.CALIBRATING)
    else:
        flag = step(inputs.flag, assessment.peak_di, threshold, m)
    state = flag.state
    detection = detection_input(assessment, state, threshold, list(inputs.library_ids))
    baseline_age_days = 0.0
    if history.baseline_set_at is not None:
        baseline_age_days = (now - history.baseline_set_at).total_seconds() / 86400.0
    joins = joins_library(
        settings,
        state=state,
        peak_di=detection.peak_di,
        threshold=threshold,
        temperature_c=temperature_c,
        library=list(inputs.library),
        baseline_age_days=baseline_age_days,
    )
    return Verdict(
        kind=MeasurementKind.BASELINE if joins else MeasurementKind.MONITOR,
        state=state,
        flag=flag,
        state_change=_change(history.state, state),
        detection=detection,
        joins_library=joins,
        sensor_faults=sensor_fault_change(inputs.sensor_faults, detection.sensor_faults),
        alarms=alarm_change(inputs.alarms, state=state.value, baseline=history.baseline),
        open_alarms=inputs.alarms,
    )
