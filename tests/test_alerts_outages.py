"""Node reachability alerts: offline after the configured time, once per outage; online when it answers again."""
from __future__ import annotations

from datetime import timedelta

from alerts.events import EventKind
from alerts.outages import check_outages
from alerts.outbox import events_of_kind
from db.nodes import record_node_health

from alerts_fixtures import T0, alerting, outbox_db  # noqa: F401

SETTINGS = alerting({"type": "mqtt", "name": "scada", "host": "127.0.0.1"}, offline_after_s=600)


def check(database, now, watching_since=T0):
    with database.write() as session:
        return [e.kind for e in check_outages(session, SETTINGS, now=now, watching_since=watching_since)]


def test_a_silent_node_is_reported_offline_once_and_online_when_it_answers(outbox_db):
    # All three nodes were last seen at T0.
    assert check(outbox_db, T0 + timedelta(minutes=9)) == []
    assert check(outbox_db, T0 + timedelta(minutes=11)) == [EventKind.NODE_OFFLINE] * 3
    assert check(outbox_db, T0 + timedelta(minutes=30)) == []  # the same outage is not reported again
    with outbox_db.write() as session:
        record_node_health(session, "node-b", online=True, seen_at=T0 + timedelta(minutes=40))
    assert check(outbox_db, T0 + timedelta(minutes=41)) == [EventKind.NODE_ONLINE]
    assert check(outbox_db, T0 + timedelta(minutes=42)) == []
    with outbox_db.session() as session:
        online, = events_of_kind(session, EventKind.NODE_ONLINE)
        offline = {e.node_id: e for e in events_of_kind(session, EventKind.NODE_OFFLINE)}
        offline_sinks = [d.sink for d in offline["node-a"].deliveries]
    assert online.node_id == "node-b" and online.payload["offline_event_id"] == str(offline["node-b"].id)
    assert online.payload["offline_for_s"] == 2400.0
    assert offline["node-a"].severity.value == "warning" and offline_sinks == ["scada"]
    # node-b goes silent again: a new outage, a new event.
    assert check(outbox_db, T0 + timedelta(minutes=52)) == [EventKind.NODE_OFFLINE]


def test_the_gateways_own_downtime_does_not_count_against_the_nodes(outbox_db):
    restarted = T0 + timedelta(hours=5)
    assert check(outbox_db, restarted + timedelta(minutes=1), watching_since=restarted) == []
    assert check(outbox_db, restarted + timedelta(minutes=11), watching_since=restarted) == [EventKind.NODE_OFFLINE] * 3
