"""Open alarms read from a real SQLite outbox, which sinks had them, and the ends a decommissioning gives."""
from __future__ import annotations

import threading
from datetime import timedelta

from sqlalchemy import select, update

from alerts.alarms import ENDED_BY, RAISED_BY, Alarm, EndCause, decommissioning_events, open_alarms, open_alarms_by_node
from alerts.events import EventKind, node_offline_event, node_online_event
from db.models import DeliveryRow, DeliveryStatus, EventRow, Severity
from db.nodes import decommission_node
from gateway.config import NodeSettings
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from tests.support.alerts_fixtures import T0, alerting, dead_receiver, put_events, put_state_events, sensor_fault_pair

HOOK = {"type": "webhook", "name": "hook", "url": "http://127.0.0.1:9/", "secret": "whsec_" + "QUJD" * 8}
LOUD = {"type": "slack", "name": "loud", "url": "http://127.0.0.1:9/", "min_severity": "critical"}


def test_suspected_then_damage_is_one_alarm_escalated_and_keeps_its_first_id(outbox_db):
    settings = alerting(HOOK, LOUD)
    suspected, damage = put_state_events(outbox_db, settings, node_ids=("node-a",),
                                         cycle=[("ok", "suspected"), ("suspected", "damage")])
    with outbox_db.session() as session:
        alarms = open_alarms(session, "node-a")
    assert alarms.damage is not None and alarms.blind is None
    assert alarms.damage.alarm_id == suspected.id and alarms.damage.latest_event_id == damage.id
    assert alarms.damage.state == "damage" and alarms.damage.routing == Severity.CRITICAL
    assert alarms.damage.raised_at == T0  # when it was first raised
    assert alarms.damage.sinks == {"hook", "loud"}  # loud had only the critical raise: it still must hear the end


def test_an_ended_alarm_is_no_longer_open_and_a_later_one_is_another(outbox_db):
    settings = alerting(HOOK)
    events = put_state_events(outbox_db, settings, node_ids=("node-a",),
                              cycle=[("ok", "damage"), ("damage", "ok"), ("ok", "suspected")])
    with outbox_db.session() as session:
        alarms = open_alarms(session, "node-a")
    assert alarms.damage.alarm_id == events[2].id and alarms.damage.state == "suspected"


def test_a_sink_whose_delivery_of_the_raise_died_still_hears_the_end(outbox_db):
    settings = alerting(HOOK, {**HOOK, "name": "other"})
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    with outbox_db.write() as session:
        session.execute(update(DeliveryRow).where(DeliveryRow.sink == "other").values(status=DeliveryStatus.DEAD))
    with outbox_db.session() as session:
        assert open_alarms(session, "node-a").damage.sinks == {"hook", "other"}


def test_offline_and_sensor_faults_are_open_until_their_ends(outbox_db):
    settings = alerting(HOOK)
    offline = node_offline_event(settings, node_id="node-b", state="ok", last_seen_at=T0, now=T0 + timedelta(hours=1))
    rx5, rx5_cleared = sensor_fault_pair(settings, "node-b", dead_receiver(5))
    rx2, _ = sensor_fault_pair(settings, "node-b", dead_receiver(2), measurement_id=9)
    put_events(outbox_db, [offline, rx5, rx2])
    with outbox_db.session() as session:
        alarms = open_alarms(session, "node-b")
    assert alarms.offline.alarm_id == offline.id
    assert [a.rx_index for a in alarms.sensor_faults] == [2, 5]
    online = node_online_event(settings, node_id="node-b", state="ok", offline_event_id=offline.id, offline_since=T0,
                               seen_at=T0 + timedelta(hours=2))
    put_events(outbox_db, [online, rx5_cleared])
    with outbox_db.session() as session:
        alarms = open_alarms(session, "node-b")
        by_node = open_alarms_by_node(session)
    assert alarms.offline is None and [a.rx_index for a in alarms.sensor_faults] == [2]
    assert set(by_node) == {"node-b"} and by_node["node-b"] == alarms


def test_decommissioning_ends_every_open_alarm_with_its_own_end_once(outbox_db):
    settings = alerting(HOOK, LOUD)
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage"), ("damage", "no_valid_baseline")])
    offline = node_offline_event(settings, node_id="node-a", state="no_valid_baseline", last_seen_at=T0,
                                 now=T0 + timedelta(hours=1))
    fault, _ = sensor_fault_pair(settings, "node-a", dead_receiver(3))
    put_events(outbox_db, [offline, fault])
    with outbox_db.session() as session:
        alarms = open_alarms(session, "node-a")
    at = T0 + timedelta(days=1)
    ends = decommissioning_events(settings, alarms, node_id="node-a", state="no_valid_baseline", decommissioned_at=at,
                                  by="admin:ops", reason="line 3 replaced")
    assert [e.kind for e in ends] == [EventKind.DAMAGE_CLEARED, EventKind.MONITORING_RESTORED, EventKind.NODE_ONLINE,
                                      EventKind.SENSOR_FAULT_CLEARED]
    for end in ends:
        assert end.payload["ended_by"] == {"cause": EndCause.DECOMMISSIONING, "by": "admin:ops",
                                           "reason": "line 3 replaced"}
        assert end.payload["occurred_at"] == at.isoformat()
        assert "line 3 replaced" in end.payload["summary"]
    damage_end = ends[0]
    assert damage_end.sinks == ("hook", "loud") and damage_end.payload["alarm_id"] == str(alarms.damage.alarm_id)
    assert ends[2].payload["online"] is False  # the offline alarm ends, the node is not back
    assert ends[3].payload["receiver"]["rx_index"] == 3 and ends[3].sinks == ("hook",)
    again = decommissioning_events(settings, alarms, node_id="node-a", state="no_valid_baseline",
                                   decommissioned_at=at + timedelta(hours=1), by="x", reason="y")
    assert [e.id for e in again] == [e.id for e in ends], "each alarm ends once, whoever ends it"
    put_events(outbox_db, ends)
    with outbox_db.session() as session:
        assert open_alarms(session, "node-a").all() == []


def test_every_alarm_kind_belongs_to_one_alarm():
    assert set(RAISED_BY.values()) == set(ENDED_BY.values()) == set(Alarm)


def test_the_gateway_noticing_a_decommissioning_ends_the_nodes_alarms_before_telling_it_once(outbox_db):
    settings = alerting(HOOK)
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    fault, _ = sensor_fault_pair(settings, "node-a", dead_receiver(3))
    put_events(outbox_db, [fault])
    with outbox_db.write() as session:
        decommission_node(session, "node-a", who="admin:ops", reason="line 3 replaced")

    def worker() -> NodeWorker:  # a fresh worker: the gateway (re)started
        return NodeWorker(NodeSettings(id="node-a", url="loop://"), outbox_db, Heartbeats(), threading.Event(),
                          alerting=settings)

    assert worker()._decommissioned() and worker()._decommissioned()  # noticed twice (a restart in between)
    with outbox_db.session() as session:
        told = [(e.kind, e.payload.get("ended_by", {}).get("cause")) for e in session.scalars(
            select(EventRow).where(EventRow.node_id == "node-a").order_by(EventRow.created_at, EventRow.id))]
        assert open_alarms(session, "node-a").all() == []
    assert told == [("damage_raised", None), ("sensor_fault", None), ("damage_cleared", "decommissioning"),
                    ("sensor_fault_cleared", "decommissioning"), ("node_decommissioned", None)]
