"""The alert payload as a contract: typed models, their published JSON Schema, and the JSON receivers get."""
from __future__ import annotations

import json
import re
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

import jsonschema_rs
import pytest
from typer.testing import CliRunner

from alerts.config import AlertingSettings
from alerts.events import (
    EventKind,
    baseline_changed_event,
    node_decommissioned_event,
    node_misconfigured_event,
    node_offline_event,
    node_online_event,
    node_recommissioned_event,
    sensor_fault_cleared_event,
    sensor_fault_event,
    sink_disabled_event,
    state_change_event,
    storage_unavailable_event,
)
from alerts.payloads import ALERT_PAYLOAD, KIND_PAYLOADS, PAYLOAD_SCHEMA, payload_json, payload_json_schema
from db.models import NodeState
from pipesentry.commands.alerts import alerts_app

DOC = Path(__file__).resolve().parents[2] / "docs" / "alerting.md"
T0 = datetime(2026, 3, 1, 12, 0, 0, 123456, tzinfo=UTC)
SETTINGS = AlertingSettings.model_validate({
    "api_base_url": "https://pipes.example.org/",
    "sinks": [{"type": "mqtt", "name": "all", "host": "127.0.0.1"}],
})
FAULT = {"rx_index": 5, "rx_angle_deg": 112.5, "kind": "no_signal", "amplitude_ratio": 0.01, "delay_s": 1e-7}


def every_kind_of_event():
    """One or more events of every kind, built as the gateway and the delivery threads build them."""
    raised = sensor_fault_event(SETTINGS, node_id="n-1", fault=FAULT, measurement_id=11, state="ok",
                                faulty_receivers=[5], consecutive=2, occurred_at=T0)
    events = [
        state_change_event(SETTINGS, node_id="n-1", from_state=NodeState.SUSPECTED, to_state=NodeState.DAMAGE,
                           measurement_id=42, peak_di=0.42, threshold=0.3, axial_mm=1820.04, angle_deg=95.0,
                           occurred_at=T0),
        state_change_event(SETTINGS, node_id="n-1", from_state="damage", to_state="ok", measurement_id=43,
                           peak_di=0.1, threshold=0.3, occurred_at=T0),
        state_change_event(SETTINGS, node_id="n-1", from_state="ok", to_state="no_valid_baseline", measurement_id=44,
                           peak_di=None, threshold=0.3, occurred_at=T0, reason="25 degC from every baseline"),
        state_change_event(SETTINGS, node_id="n-1", from_state="no_valid_baseline", to_state="ok",
                           measurement_id=None, peak_di=0.01, threshold=None, occurred_at=T0),
        node_offline_event(SETTINGS, node_id="n-1", state="damage", last_seen_at=T0, now=T0 + timedelta(hours=3)),
        node_online_event(SETTINGS, node_id="n-1", state="ok", offline_event_id=uuid.UUID(int=5), offline_since=T0,
                          seen_at=T0 + timedelta(seconds=75)),
        node_offline_event(SETTINGS, node_id="n-2", state="commissioning", last_seen_at=T0,
                           now=T0 + timedelta(minutes=10), never_seen=True),
        node_online_event(SETTINGS, node_id="n-2", state="commissioning", offline_event_id=uuid.UUID(int=6),
                          offline_since=T0, seen_at=T0 + timedelta(minutes=12), first_seen=True),
        baseline_changed_event(SETTINGS, node_id="n-1", baseline_id=3, measurement_id=9, previous_measurement_id=None,
                               created_by="operator:kim", reason="re-baselined", state="ok", occurred_at=T0),
        node_decommissioned_event(SETTINGS, node_id="n-1", state="ok", decommissioned_at=T0, by="admin",
                                  reason="pipe replaced"),
        node_recommissioned_event(SETTINGS, node_id="n-1", state="ok", decommissioned_at=T0,
                                  occurred_at=T0 + timedelta(days=1)),
        node_misconfigured_event(SETTINGS, node_id="n-1", state="ok", boot_id=0x9E3779B9, occurred_at=T0,
                                 problems=["node_id: the node on /dev/ttyUSB1 reports 'n-2', configured 'n-1'"]),
        sink_disabled_event(SETTINGS, sink_name="old-hook", endpoint_fingerprint="ab12", status_code=410,
                            occurred_at=T0),
        storage_unavailable_event(SETTINGS, since=T0, until=T0 + timedelta(minutes=20), failed_writes=4,
                                  reason="StorageFull: SQLite: database or disk is full"),
        raised,
        sensor_fault_cleared_event(SETTINGS, node_id="n-1", raised_event_id=raised.id,
                                   raised_receiver=raised.payload["receiver"], raised_measurement_id=11,
                                   measurement_id=13, state="ok", faulty_receivers=[], consecutive=2, occurred_at=T0),
    ]
    assert None not in events
    return events


def doc_schema() -> dict:
    section = DOC.read_text().split("### Payload schema", 1)[1]
    return json.loads(re.search(r"```json\n(.*?)\n```", section, re.DOTALL).group(1))


def test_the_schema_published_in_the_docs_is_the_models_schema():
    assert doc_schema() == payload_json_schema()


def test_pipesentry_alerts_schema_prints_the_published_schema():
    result = CliRunner().invoke(alerts_app, ["schema"])
    assert result.exit_code == 0 and json.loads(result.output) == payload_json_schema()


def test_every_event_kind_has_its_payload_model():
    kinds = set()
    for model in KIND_PAYLOADS:
        kinds |= set(model.model_fields["kind"].annotation.__args__)
    assert kinds == {str(kind) for kind in EventKind}


@pytest.mark.parametrize("event", every_kind_of_event(), ids=lambda e: e.payload["kind"])
def test_every_payload_the_builders_make_is_its_model_and_valid_against_the_schema(event):
    model = ALERT_PAYLOAD.validate_python(event.payload)
    assert payload_json(model) == event.payload  # the stored JSON is the model's, field for field
    assert json.dumps(payload_json(model)) == json.dumps(event.payload)  # ... in the same order
    assert event.payload["schema"] == PAYLOAD_SCHEMA and event.payload["event_id"] == str(event.id)
    jsonschema_rs.Draft202012Validator(payload_json_schema()).validate(event.payload)


def test_the_example_in_the_docs_is_a_valid_payload():
    events = DOC.read_text().split("### Payload schema", 1)[0].split("## Events", 1)[1]
    example = json.loads(re.search(r"```json\n(.*?)\n```", events, re.DOTALL).group(1))
    jsonschema_rs.Draft202012Validator(payload_json_schema()).validate(example)
    assert ALERT_PAYLOAD.validate_python(example).kind == "damage_raised"


@pytest.mark.parametrize(
    "change",
    [
        {"node_id": None},  # a damage alert is always about a node
        {"state": "broken"},  # not a node state
        {"kind": "damage_exploded"},
        {"occurred_at": 1772366400},  # an instant is ISO 8601 text
        {"detection": {"peak_di": "high", "threshold": 0.3, "di_over_threshold": None}},
    ],
)
def test_the_schema_refuses_a_payload_that_breaks_the_contract(change):
    payload = {**every_kind_of_event()[0].payload, **change}
    assert not jsonschema_rs.Draft202012Validator(payload_json_schema()).is_valid(payload)


def test_a_receiver_may_meet_a_field_added_later_in_the_same_version():
    payload = every_kind_of_event()[0].payload
    payload = {**payload, "location": {**payload["location"], "uncertainty_mm": 4.0}, "new_field": 1}
    assert jsonschema_rs.Draft202012Validator(payload_json_schema()).is_valid(payload)


def test_an_optional_field_that_is_not_known_is_left_out_not_sent_as_null():
    blind, restored = every_kind_of_event()[2:4]
    assert blind.payload["reason"] == "25 degC from every baseline" and "reason" not in restored.payload
    assert restored.payload["links"] == {"node": "https://pipes.example.org/api/v1/nodes/n-1"}  # no measurement
    assert restored.payload["measurement_id"] is None and restored.payload["location"] is None  # these stay null
    offline, online, never_seen, first_seen = every_kind_of_event()[4:8]
    assert "never_seen" not in offline.payload and "first_seen" not in online.payload
    assert never_seen.payload["never_seen"] is True and first_seen.payload["first_seen"] is True


def test_a_node_never_seen_is_said_so_in_its_offline_and_first_online_summaries():
    offline, _online, never_seen, first_seen = every_kind_of_event()[4:8]
    assert offline.payload["summary"].startswith("node n-1 offline: not seen for 3.0 h")
    assert never_seen.payload["summary"] == (
        "node n-2 offline: never answered, watched for 10 min (since 2026-03-01 12:00:00 UTC)")
    assert never_seen.payload["last_seen_at"] == T0.isoformat() and never_seen.payload["offline_for_s"] == 600.0
    assert first_seen.payload["summary"] == (
        "node n-2 answered for the first time, after 12 min watched, state commissioning")


def test_the_location_carries_the_estimates_90_percent_region_when_the_detection_has_one():
    with_region = state_change_event(
        SETTINGS, node_id="n-1", from_state="ok", to_state="suspected", measurement_id=41, peak_di=0.05,
        threshold=0.03, axial_mm=150.2, angle_deg=45.0, occurred_at=T0,
        region={"coverage": 0.9, "axial_half_mm": 400.0, "circumferential_half_mm": 180.0, "localized": False,
                "reason": "a competing peak"})
    assert with_region.payload["location"] == {"axial_mm": 150.2, "angle_deg": 45.0, "axial_half_mm": 400.0,
                                               "circumferential_half_mm": 180.0, "localized": False}
    jsonschema_rs.Draft202012Validator(payload_json_schema()).validate(with_region.payload)
    without = every_kind_of_event()[0]
    assert set(without.payload["location"]) == {"axial_mm", "angle_deg"}  # optional: left out, not null
