"""The cycle's decision alone: no node, no database — real assessments of synthetic records in, a verdict out."""
from __future__ import annotations

import uuid
from dataclasses import replace
from datetime import UTC, datetime, timedelta

import pytest

from alerts.config import AlertingSettings
from alerts.events import EventKind
from alerts.sensor_faults import OpenFault, SensorFaultHistory
from db.models import MeasurementKind, NodeState
from gateway.assessment import assess_settings
from gateway.config import NodeSettings, ThresholdSettings
from gateway.decision import (
    COMMISSIONING_BASELINE,
    MonitoringInputs,
    NodeHistory,
    decide_commissioning,
    decide_monitoring,
    is_commissioning,
)
from gateway.flagging import FlagState
from imaging.pipeline import Assessment, assess
from tests.support.synthetic import baseline_and_scatterer, mock_pipe_record

NOW = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)
THRESHOLD = 0.02
BASELINE_ID = 7
ALERTING = AlertingSettings.model_validate(
    {"sinks": [{"type": "webhook", "name": "hook", "url": "http://127.0.0.1:9/", "secret": "whsec_" + "QUJD" * 8}]}
)
NODE = NodeSettings(id="n", url="loop://", threshold=ThresholdSettings(mode="absolute", absolute=THRESHOLD,
                                                                       hysteresis_count=2))


@pytest.fixture(scope="module")
def records():
    base, notched = baseline_and_scatterer(200.0, 90.0)
    dead = base.traces.copy()
    dead[5] = 0.0  # receiver 5 lost its transducer
    return {"baseline": base, "notched": notched, "dead_rx5": replace(base, traces=dead)}


@pytest.fixture(scope="module")
def assessments(records) -> dict[str, Assessment]:
    base = records["baseline"]
    settings = assess_settings(NODE, THRESHOLD, None)
    warm, cool_library = mock_pipe_record(45.0, 2), [mock_pipe_record(20.0, 1)]
    return {
        "sound": assess(base, [base], settings),
        "notched": assess(records["notched"], [base], settings),
        "dead_rx5": assess(records["dead_rx5"], [base], settings),
        "blind": assess(warm, cool_library, settings),  # 25 degC warmer than any baseline: abstains
    }


def history(state=NodeState.OK, *, active=BASELINE_ID, n_baselines=1, age_days=1.0) -> NodeHistory:
    return NodeHistory(state, active, NOW - timedelta(days=age_days) if active else None, n_baselines)


def inputs(records, *, flag=None, threshold=THRESHOLD, library_temps=(20.0,), sensor=None) -> MonitoringInputs:
    library = [replace(records["baseline"], temperature_c=t) for t in library_temps]
    return MonitoringInputs(flag or FlagState(), threshold, [BASELINE_ID + k for k in range(len(library))], library,
                            sensor or SensorFaultHistory(ALERTING.sensor_fault_count, (), {}))


def monitor(records, assessment, *, node=NODE, state=NodeState.OK, temperature_c=20.5, age_days=1.0, **kw):
    return decide_monitoring(node, history(state, age_days=age_days), inputs(records, **kw), assessment,
                             temperature_c=temperature_c, now=NOW)


def kinds(verdict, measurement_id=100):
    return [e.kind for e in verdict.events(ALERTING, node_id="n", measurement_id=measurement_id, now=NOW)]


# ------------------------------------------------------------------ commissioning
def test_a_node_without_an_active_baseline_or_with_too_few_baselines_is_commissioning():
    node = NODE.model_copy(update={"commissioning_count": 3})
    assert is_commissioning(node, history(active=None, n_baselines=5))
    assert is_commissioning(node, history(n_baselines=2))
    assert not is_commissioning(node, history(n_baselines=3))


def test_the_first_commissioning_record_becomes_the_active_baseline():
    verdict = decide_commissioning(NODE, history(NodeState.COMMISSIONING, active=None, n_baselines=0))
    assert verdict.kind == MeasurementKind.BASELINE and verdict.activate_baseline == COMMISSIONING_BASELINE
    assert verdict.state == NodeState.OK and verdict.state_change.to_state == NodeState.OK  # absolute: monitors at once
    assert verdict.detection is None and kinds(verdict) == []  # setting a node up alerts nobody


def test_commissioning_ends_with_the_last_of_n_baselines_and_a_calibrated_node_then_calibrates():
    node = NodeSettings(id="n", url="loop://", commissioning_count=3)  # threshold mode calibrated (default)
    second = decide_commissioning(node, history(NodeState.COMMISSIONING, n_baselines=1))
    assert (second.state, second.state_change, second.activate_baseline) == (NodeState.COMMISSIONING, None, None)
    last = decide_commissioning(node, history(NodeState.COMMISSIONING, n_baselines=2))
    assert last.state == NodeState.CALIBRATING and last.state_change.from_state == NodeState.COMMISSIONING


# ------------------------------------------------------------------ monitoring
def test_a_sound_reading_keeps_an_ok_node_ok_and_alerts_nobody(records, assessments):
    verdict = monitor(records, assessments["sound"])
    assert verdict.kind == MeasurementKind.MONITOR and verdict.state == NodeState.OK
    assert verdict.state_change is None and kinds(verdict) == []
    assert verdict.detection.threshold == THRESHOLD and verdict.detection.peak_di < THRESHOLD
    assert verdict.detection.baseline_measurement_id == BASELINE_ID


def test_a_notch_makes_the_node_suspected_then_damage_with_an_alert_at_each_step(records, assessments):
    first = monitor(records, assessments["notched"])
    assert first.state == NodeState.SUSPECTED and kinds(first) == [EventKind.DAMAGE_RAISED]
    second = monitor(records, assessments["notched"], state=first.state, flag=first.flag)
    assert second.state == NodeState.DAMAGE and second.state_change.from_state == NodeState.SUSPECTED
    (event,) = second.events(ALERTING, node_id="n", measurement_id=101, now=NOW)
    assert event.severity == "critical" and event.payload["measurement_id"] == 101
    assert event.payload["location"]["axial_mm"] == pytest.approx(200.0, abs=15.0)
    assert event.payload["detection"]["threshold"] == THRESHOLD


def test_damage_clears_only_after_m_sound_readings_and_then_says_so(records, assessments):
    damage = FlagState(NodeState.DAMAGE, above=2)
    once = monitor(records, assessments["sound"], state=NodeState.DAMAGE, flag=damage)
    assert once.state == NodeState.DAMAGE and kinds(once) == []
    twice = monitor(records, assessments["sound"], state=NodeState.DAMAGE, flag=once.flag)
    assert twice.state == NodeState.OK and kinds(twice) == [EventKind.DAMAGE_CLEARED]


def test_an_abstaining_imaging_makes_the_node_blind_with_the_reason_in_its_alert(records, assessments):
    verdict = monitor(records, assessments["blind"], temperature_c=45.0)
    assert verdict.state == NodeState.NO_VALID_BASELINE and verdict.detection.peak_di is None
    (event,) = verdict.events(ALERTING, node_id="n", measurement_id=100, now=NOW)
    assert event.kind == EventKind.MONITORING_BLIND and event.payload["reason"] == verdict.detection.abstain_reason
    assert verdict.kind == MeasurementKind.MONITOR  # a blind reading never teaches the library


def test_without_a_threshold_yet_the_node_calibrates_and_raises_nothing(records, assessments):
    verdict = monitor(records, assessments["notched"], state=NodeState.CALIBRATING, threshold=None)
    assert verdict.state == NodeState.CALIBRATING and verdict.state_change is None
    assert verdict.detection.threshold is None and verdict.detection.peak_di > THRESHOLD and kinds(verdict) == []


def test_a_clearly_healthy_reading_at_a_new_temperature_is_stored_as_a_library_baseline(records, assessments):
    verdict = monitor(records, assessments["sound"], temperature_c=25.0)
    assert verdict.joins_library and verdict.kind == MeasurementKind.BASELINE
    assert verdict.activate_baseline is None  # it joins the library; the active baseline stays
    old_baseline = monitor(records, assessments["sound"], temperature_c=25.0, age_days=45.0)
    assert not old_baseline.joins_library and old_baseline.kind == MeasurementKind.MONITOR


def test_a_receiver_faulty_in_consecutive_readings_raises_a_sensor_fault_alert(records, assessments):
    result = assessments["dead_rx5"]
    assert [f.rx_index for f in result.sensor_faults] == [5]
    once = monitor(records, result)
    assert kinds(once) == []  # once could be a glitch (sensor_fault_count = 2)
    seen = SensorFaultHistory(2, ({5: once.detection.sensor_faults[0]},), {})
    twice = monitor(records, result, sensor=seen)
    (event,) = twice.events(ALERTING, node_id="n", measurement_id=100, now=NOW)
    assert event.kind == EventKind.SENSOR_FAULT and event.payload["receiver"]["rx_index"] == 5
    assert event.payload["faulty_receivers"] == [5] and event.payload["measurement_id"] == 100


def test_an_open_sensor_fault_clears_after_consecutive_healthy_readings(records, assessments):
    raised = OpenFault(uuid.uuid4(), {"rx_index": 5, "kind": "no_signal", "rx_angle_deg": 112.5}, 90)
    verdict = monitor(records, assessments["sound"], sensor=SensorFaultHistory(2, ({},), {5: raised}))
    (event,) = verdict.events(ALERTING, node_id="n", measurement_id=100, now=NOW)
    assert event.kind == EventKind.SENSOR_FAULT_CLEARED and event.payload["raised_event_id"] == str(raised.event_id)


def test_the_same_verdict_gives_the_same_event_ids_for_the_same_measurement(records, assessments):
    verdict = monitor(records, assessments["notched"])
    first = verdict.events(ALERTING, node_id="n", measurement_id=100, now=NOW)
    again = verdict.events(ALERTING, node_id="n", measurement_id=100, now=NOW + timedelta(seconds=5))
    other = verdict.events(ALERTING, node_id="n", measurement_id=101, now=NOW)
    assert [e.id for e in first] == [e.id for e in again] != [e.id for e in other]
