"""Event builders: which transitions alert, with what severity, stable ids, location, DI and links."""
from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta

import pytest

from alerts.config import AlertingSettings
from alerts.events import (
    EventKind,
    baseline_changed_event,
    node_misconfigured_event,
    node_offline_event,
    node_online_event,
    sensor_fault_cleared_event,
    sensor_fault_event,
    sink_disabled_event,
    state_change_event,
)
from db.models import Severity

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
SETTINGS = AlertingSettings.model_validate({
    "api_base_url": "https://pipes.example.org/",
    "sinks": [
        {"type": "mqtt", "name": "all", "host": "127.0.0.1"},
        {"type": "mqtt", "name": "loud-only", "host": "127.0.0.1", "min_severity": "critical"},
        {"type": "mqtt", "name": "warnings", "host": "127.0.0.1", "min_severity": "warning"},
    ],
})


def damage(to_state="damage", from_state="suspected", measurement_id=42, **kw):
    args = dict(node_id="node-7", from_state=from_state, to_state=to_state, measurement_id=measurement_id,
                peak_di=0.42, threshold=0.3, axial_mm=1820.04, angle_deg=95.0, occurred_at=T0)
    args.update(kw)
    return state_change_event(SETTINGS, **args)


def test_damage_event_carries_location_di_against_threshold_and_api_links():
    event = damage()
    assert event.kind == EventKind.DAMAGE_RAISED and event.severity == Severity.CRITICAL
    p = event.payload
    assert p["node_id"] == "node-7" and p["state"] == "damage" and p["previous_state"] == "suspected"
    assert p["location"] == {"axial_mm": 1820.0, "angle_deg": 95.0}
    assert p["detection"] == {"peak_di": 0.42, "threshold": 0.3, "di_over_threshold": 1.4}
    assert p["links"]["measurement"] == "https://pipes.example.org/api/v1/measurements/42"
    assert p["links"]["di_map_png"] == "https://pipes.example.org/api/v1/measurements/42/di-maps/gateway.png"
    assert p["event_id"] == str(event.id)
    assert "DAMAGE on node node-7" in p["summary"] and "1820 mm" in p["summary"] and "0.42" in p["summary"]
    assert event.sinks == ("all", "loud-only", "warnings")


def test_the_same_fact_always_gets_the_same_id_and_another_fact_another():
    assert damage().id == damage().id
    assert damage().id != damage(measurement_id=43).id
    assert damage().id != damage(to_state="suspected", from_state="ok").id


@pytest.mark.parametrize(
    "from_state, to_state, kind, severity, sinks",
    [
        ("ok", "suspected", EventKind.DAMAGE_RAISED, Severity.WARNING, ("all", "warnings")),
        ("suspected", "damage", EventKind.DAMAGE_RAISED, Severity.CRITICAL, ("all", "loud-only", "warnings")),
        # a clearing goes wherever the alarm it clears went
        ("damage", "ok", EventKind.DAMAGE_CLEARED, Severity.INFO, ("all", "loud-only", "warnings")),
        ("suspected", "ok", EventKind.DAMAGE_CLEARED, Severity.INFO, ("all", "warnings")),
        ("damage", "no_valid_baseline", EventKind.MONITORING_BLIND, Severity.WARNING, ("all", "warnings")),
        ("no_valid_baseline", "ok", EventKind.MONITORING_RESTORED, Severity.INFO, ("all", "warnings")),
    ],
)
def test_transitions_map_to_kinds_severities_and_routes(from_state, to_state, kind, severity, sinks):
    event = damage(to_state=to_state, from_state=from_state)
    assert (event.kind, event.severity, event.sinks) == (kind, severity, sinks)


@pytest.mark.parametrize("from_state, to_state", [("commissioning", "calibrating"), ("calibrating", "ok"), ("ok", "ok")])
def test_commissioning_and_non_changes_raise_nothing(from_state, to_state):
    assert damage(to_state=to_state, from_state=from_state) is None


def test_unknown_location_and_missing_threshold_read_plainly():
    event = damage(axial_mm=None, angle_deg=None, threshold=None)
    assert event.payload["location"] is None
    assert "location unknown" in event.payload["summary"] and "no threshold yet" in event.payload["summary"]


def test_going_blind_says_why_the_imaging_abstained():
    why = "the record is stretched +0.23% against the closest baseline (about 23 degC in steel)"
    event = damage(from_state="ok", to_state="no_valid_baseline", peak_di=None, reason=why)
    assert event.kind == EventKind.MONITORING_BLIND and event.payload["reason"] == why
    assert why in event.payload["summary"]
    plain = damage(from_state="ok", to_state="no_valid_baseline", peak_di=None)
    assert "reason" not in plain.payload and "no valid baseline" in plain.payload["summary"]


def test_an_outage_has_one_offline_id_and_its_online_event_points_back():
    seen = T0 - timedelta(minutes=30)
    offline = node_offline_event(SETTINGS, node_id="n1", state="ok", last_seen_at=seen, now=T0)
    again = node_offline_event(SETTINGS, node_id="n1", state="ok", last_seen_at=seen, now=T0 + timedelta(minutes=5))
    assert offline.id == again.id and offline.severity == Severity.WARNING
    assert offline.payload["online"] is False and offline.payload["offline_for_s"] == 1800.0
    online = node_online_event(SETTINGS, node_id="n1", state="ok", offline_event_id=offline.id, offline_since=seen,
                               seen_at=T0 + timedelta(minutes=10))
    assert online.kind == EventKind.NODE_ONLINE and online.payload["online"] is True
    assert online.payload["offline_event_id"] == str(offline.id) and online.sinks == offline.sinks
    assert "40 min" in online.payload["summary"]


def test_baseline_change_links_the_new_baseline_measurement():
    event = baseline_changed_event(SETTINGS, node_id="n1", baseline_id=5, measurement_id=77, previous_measurement_id=3,
                                   created_by="operator:alice", reason="pipe repaired", state="ok", occurred_at=T0)
    assert event.kind == EventKind.BASELINE_CHANGED and event.severity == Severity.INFO
    assert event.payload["links"]["measurement"].endswith("/api/v1/measurements/77")
    assert event.sinks == ("all",) and "pipe repaired" in event.payload["summary"]


def test_a_misconfigured_node_is_a_warning_listing_its_problems_once_per_boot():
    problems = ["node_id: the node on /dev/ttyUSB3 reports 'pipe-x', configured 'pipe-a'"]
    event = node_misconfigured_event(SETTINGS, node_id="pipe-a", state="ok", problems=problems, boot_id=7,
                                     occurred_at=T0)
    assert event.kind == EventKind.NODE_MISCONFIGURED and event.severity == Severity.WARNING
    assert event.sinks == ("all", "warnings") and event.payload["problems"] == problems
    assert event.payload["summary"] == "node pipe-a misconfigured: " + problems[0]
    again = node_misconfigured_event(SETTINGS, node_id="pipe-a", state="ok", problems=problems, boot_id=7)
    next_boot = node_misconfigured_event(SETTINGS, node_id="pipe-a", state="ok", problems=problems, boot_id=8)
    assert again.id == event.id != next_boot.id


def test_a_disabled_sink_is_reported_to_the_others_only():
    event = sink_disabled_event(SETTINGS, sink_name="warnings", endpoint_fingerprint="abc", status_code=410)
    assert event.sinks == ("all",) and event.payload["sink"] == "warnings"
    assert isinstance(event.id, uuid.UUID)


def test_a_sensor_fault_names_node_receiver_and_fault_and_its_clearing_points_back_to_it():
    fault = {"rx_index": 3, "rx_angle_deg": 67.5, "kind": "timing", "amplitude_ratio": 0.97, "delay_s": 4.1e-6}
    raised = sensor_fault_event(SETTINGS, node_id="n1", fault=fault, measurement_id=88, state="ok",
                                faulty_receivers=[3, 1], consecutive=2, occurred_at=T0)
    assert raised.kind == EventKind.SENSOR_FAULT and raised.severity == Severity.WARNING
    assert raised.sinks == ("all", "warnings") and raised.payload["receiver"] == fault
    assert raised.payload["faulty_receivers"] == [1, 3]
    assert raised.payload["links"]["measurement"].endswith("/api/v1/measurements/88")
    assert "n1 receiver 3 (68 deg) faulty: timing (direct arrival shifted +4.10 us)" in raised.payload["summary"]
    cleared = sensor_fault_cleared_event(SETTINGS, node_id="n1", raised_event_id=raised.id,
                                         raised_receiver=raised.payload["receiver"], raised_measurement_id=88,
                                         measurement_id=91, state="ok", faulty_receivers=[1], consecutive=2)
    assert cleared.kind == EventKind.SENSOR_FAULT_CLEARED and cleared.severity == Severity.INFO
    assert cleared.sinks == raised.sinks, "the clearing goes wherever the fault went"
    assert cleared.payload["receiver"] == fault and cleared.payload["raised_event_id"] == str(raised.id)
    assert "healthy again" in cleared.payload["summary"] and "was timing since measurement 88" in cleared.payload["summary"]


def test_sensor_fault_ids_are_stable_per_node_receiver_and_measurement():
    def raised(node_id="n1", rx=3, measurement_id=88):
        fault = {"rx_index": rx, "rx_angle_deg": 0.0, "kind": "no_signal", "amplitude_ratio": 0.0, "delay_s": 0.0}
        return sensor_fault_event(SETTINGS, node_id=node_id, fault=fault, measurement_id=measurement_id,
                                  state="ok", faulty_receivers=[rx], consecutive=2).id
    assert raised() == raised()
    assert len({raised(), raised(node_id="n2"), raised(rx=4), raised(measurement_id=89)}) == 4


def test_a_sensor_fault_without_a_receiver_index_is_refused():
    with pytest.raises(ValueError, match="rx_index"):
        sensor_fault_event(SETTINGS, node_id="n1", fault={"kind": "no_signal"}, measurement_id=1, state="ok",
                           faulty_receivers=[], consecutive=2)


def test_decommissioning_and_recommissioning_are_told_once_each_with_who_and_why():
    from alerts.events import node_decommissioned_event, node_recommissioned_event
    from alerts.mqtt import mqtt_publications
    from alerts.outbox import OutboxEvent
    from alerts.slack import slack_text

    at = T0 - timedelta(days=1)
    gone = node_decommissioned_event(SETTINGS, node_id="node-7", state="damage", decommissioned_at=at,
                                     by="admin:kim", reason="line 3 replaced")
    again = node_decommissioned_event(SETTINGS, node_id="node-7", state="damage", decommissioned_at=at,
                                      by="admin:kim", reason="line 3 replaced")
    back = node_recommissioned_event(SETTINGS, node_id="node-7", state="damage", decommissioned_at=at, occurred_at=T0)
    assert gone.id == again.id != back.id  # a restart that sees the same decommissioning adds nothing
    assert gone.kind == EventKind.NODE_DECOMMISSIONED and gone.severity == Severity.INFO
    assert gone.payload["decommissioned"] == {"at": at.isoformat(), "by": "admin:kim", "reason": "line 3 replaced"}
    assert "admin:kim" in gone.payload["summary"] and "line 3 replaced" in gone.payload["summary"]
    assert back.payload["decommissioned_since"] == at.isoformat() and "back in service" in back.payload["summary"]
    item = OutboxEvent(1, "scada", 0, None, gone.id, "node-7", gone.kind, gone.severity, gone.payload, at)
    ((topic, message, retained),) = mqtt_publications(SETTINGS.sinks[0], item)  # "all": an mqtt sink
    assert (topic, retained) == ("pipesentry/nodes/node-7/events", False)  # the state topic is the current state
    assert message["decommissioned"]["by"] == "admin:kim"
    assert gone.sinks == ("all",)  # info goes where info is wanted
    assert slack_text(item).startswith(":no_entry_sign: node node-7 decommissioned by admin:kim")
