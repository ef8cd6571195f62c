"""The cycle's decision alone: no node, no database — real assessments of synthetic records in, a verdict out."""
from __future__ import annotations

import uuid
from dataclasses import replace
from datetime import UTC, datetime, timedelta

import pytest

from alerts.alarms import Alarm, BaselineSet, NodeAlarms, OpenAlarm
from alerts.config import AlertingSettings
from alerts.events import EventKind
from alerts.sensor_faults import OpenFault, SensorFaultHistory
from db.models import MeasurementKind, NodeState, Severity
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
    set_at = NOW - timedelta(days=age_days) if active else None
    record = BaselineSet(40, set_at, "alice", "clamp repaired") if set_at else None
    return NodeHistory(state, active, set_at, n_baselines, baseline=record)


def open_alarm(alarm=Alarm.DAMAGE, state="damage", *, days_ago=2.0, sinks=("hook",)) -> OpenAlarm:
    """An alarm raised ``days_ago`` (before the default baseline, set a day ago)."""
    routing = {"suspected": Severity.WARNING, "damage": Severity.CRITICAL}.get(state, Severity.WARNING)
    eid = uuid.uuid5(uuid.NAMESPACE_URL, f"{alarm}/{state}/{days_ago}")
    raised = NOW - timedelta(days=days_ago)
    return OpenAlarm(alarm, eid, eid, raised, routing, {"state": state, "occurred_at": raised.isoformat()},
                     frozenset(sinks))


def alarms_of(state: NodeState) -> NodeAlarms:
    """The alarms open for a node whose alarms followed its state so far."""
    if state in (NodeState.SUSPECTED, NodeState.DAMAGE):
        return NodeAlarms(damage=open_alarm(state=state.value))
    if state == NodeState.NO_VALID_BASELINE:
        return NodeAlarms(blind=open_alarm(Alarm.BLIND, "no_valid_baseline"))
    return NodeAlarms()


def inputs(records, *, flag=None, threshold=THRESHOLD, library_temps=(20.0,), sensor=None,
           alarms=None) -> MonitoringInputs:
    library = [replace(records["baseline"], temperature_c=t) for t in library_temps]
    return MonitoringInputs(flag or FlagState(), threshold, [BASELINE_ID + k for k in range(len(library))], library,
                            sensor or SensorFaultHistory(ALERTING.sensor_fault_count, (), {}),
                            alarms=alarms if alarms is not None else NodeAlarms())


def monitor(records, assessment, *, node=NODE, state=NodeState.OK, temperature_c=20.5, age_days=1.0, alarms=None,
            **kw):
    alarms = alarms_of(state) if alarms is None else alarms
    return decide_monitoring(node, history(state, age_days=age_days), inputs(records, alarms=alarms, **kw), assessment,
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


# ------------------------------------------------------------------ alarms that end
def events(verdict, measurement_id=100):
    return {e.kind: e for e in verdict.events(ALERTING_TWO, node_id="n", measurement_id=measurement_id, now=NOW)}


ALERTING_TWO = AlertingSettings.model_validate({"sinks": [
    {"type": "webhook", "name": "hook", "url": "http://127.0.0.1:9/", "secret": "whsec_" + "QUJD" * 8},
    {"type": "slack", "name": "chat", "url": "http://127.0.0.1:9/", "min_severity": "critical"},
]})


def test_a_damaged_node_re_baselined_calibrates_and_its_damage_alarm_ends_by_the_new_baseline(records, assessments):
    # The alarm was raised two days ago; an operator set a new baseline a day ago ("clamp repaired").
    alarm = open_alarm(state="damage", sinks=("hook", "chat"))
    verdict = monitor(records, assessments["sound"], node=NodeSettings(id="n", url="loop://"), state=NodeState.DAMAGE,
                      threshold=None, alarms=NodeAlarms(damage=alarm))
    assert verdict.state == NodeState.CALIBRATING
    (cleared,) = events(verdict).values()
    assert cleared.kind == EventKind.DAMAGE_CLEARED
    p = cleared.payload
    assert p["ended_by"] == {"cause": "rebaseline", "by": "alice", "reason": "clamp repaired", "baseline_id": 40}
    assert p["alarm_id"] == str(alarm.alarm_id) and p["state"] == "calibrating" and p["previous_state"] == "damage"
    assert p["routing_severity"] == "critical" and set(cleared.sinks) == {"hook", "chat"}
    assert "new baseline by alice: clamp repaired" in p["summary"]


def test_an_alarm_ends_once_whichever_measurement_ends_it(records, assessments):
    alarm = NodeAlarms(damage=open_alarm())
    first = monitor(records, assessments["sound"], state=NodeState.DAMAGE, threshold=None, alarms=alarm)
    later = monitor(records, assessments["sound"], state=NodeState.DAMAGE, threshold=None, alarms=alarm)
    assert [e.id for e in events(first, 100).values()] == [e.id for e in events(later, 200).values()]


def test_a_blind_node_re_baselined_at_the_new_temperature_ends_its_blind_alarm(records, assessments):
    verdict = monitor(records, assessments["sound"], node=NodeSettings(id="n", url="loop://"),
                      state=NodeState.NO_VALID_BASELINE, threshold=None)
    assert verdict.state == NodeState.CALIBRATING
    (restored,) = events(verdict).values()
    assert restored.kind == EventKind.MONITORING_RESTORED and restored.payload["ended_by"]["cause"] == "rebaseline"
    assert restored.payload["alarm"] == "blind"


def test_a_damage_alarm_kept_open_through_a_blind_spell_ends_with_it_when_the_pipe_reads_sound(records, assessments):
    # damage, then blind (the damage alarm stays open: blind is not sound), then sound readings.
    both = NodeAlarms(damage=open_alarm(days_ago=0.5), blind=open_alarm(Alarm.BLIND, "no_valid_baseline", days_ago=0.2))
    verdict = monitor(records, assessments["sound"], state=NodeState.NO_VALID_BASELINE, alarms=both)
    assert verdict.state == NodeState.OK
    got = events(verdict)
    assert set(got) == {EventKind.DAMAGE_CLEARED, EventKind.MONITORING_RESTORED}
    assert all(e.payload["ended_by"] == {"cause": "recovery"} for e in got.values())  # raised after the baseline
    assert "chat" in got[EventKind.DAMAGE_CLEARED].sinks  # routed like the critical alarm it ends


def test_going_blind_keeps_the_damage_alarm_and_raises_the_blind_one(records, assessments):
    verdict = monitor(records, assessments["blind"], state=NodeState.DAMAGE, temperature_c=45.0)
    assert list(events(verdict)) == [EventKind.MONITORING_BLIND]


def test_a_blind_node_reading_damage_ends_the_blind_alarm_and_raises_damage(records, assessments):
    verdict = monitor(records, assessments["notched"], state=NodeState.NO_VALID_BASELINE)
    assert verdict.state == NodeState.SUSPECTED
    assert list(events(verdict)) == [EventKind.MONITORING_RESTORED, EventKind.DAMAGE_RAISED]


def test_a_node_in_damage_without_an_open_alarm_raises_it_again(records, assessments):
    # Decommissioned in damage (which ended its alarm), recommissioned, still above the threshold.
    verdict = monitor(records, assessments["notched"], state=NodeState.DAMAGE, flag=FlagState(NodeState.DAMAGE, above=3),
                      alarms=NodeAlarms())
    assert verdict.state == NodeState.DAMAGE and verdict.state_change is None
    (raised,) = events(verdict).values()
    assert raised.kind == EventKind.DAMAGE_RAISED and raised.severity == Severity.CRITICAL


def test_an_escalation_keeps_the_alarm_id_of_the_first_raise(records, assessments):
    suspected = open_alarm(state="suspected")
    verdict = monitor(records, assessments["notched"], state=NodeState.SUSPECTED,
                      flag=FlagState(NodeState.SUSPECTED, above=1), alarms=NodeAlarms(damage=suspected))
    assert verdict.state == NodeState.DAMAGE
    (raised,) = events(verdict).values()
    assert raised.payload["alarm_id"] == str(suspected.alarm_id) and raised.id != suspected.alarm_id


def test_with_an_absolute_threshold_a_new_baseline_ends_the_alarm_once_readings_are_sound(records, assessments):
    damage = FlagState(NodeState.DAMAGE, above=2)
    once = monitor(records, assessments["sound"], state=NodeState.DAMAGE, flag=damage)
    assert events(once) == {}  # hysteresis: M sound readings
    twice = monitor(records, assessments["sound"], state=NodeState.DAMAGE, flag=once.flag)
    (cleared,) = events(twice).values()
    assert cleared.payload["ended_by"]["cause"] == "rebaseline"  # the alarm predates the baseline
