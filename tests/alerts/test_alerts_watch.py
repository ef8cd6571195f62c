"""Facts the gateway finds in the database: node outages (offline, back online) and new baselines."""
from __future__ import annotations

from datetime import timedelta

from alerts.events import EventKind
from alerts.outages import check_outages
from alerts.outbox import events_of_kind
from db.nodes import record_node_health
from tests.support.alerts_fixtures import T0, alerting

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


def test_a_decommissioned_node_is_not_reported_offline_until_it_is_back_in_service(outbox_db):
    from db.nodes import decommission_node, recommission_node

    with outbox_db.write() as session:
        decommission_node(session, "node-c", who="admin:ops", reason="removed with the old line", now=T0)
    assert check(outbox_db, T0 + timedelta(minutes=11)) == [EventKind.NODE_OFFLINE] * 2  # node-a, node-b
    with outbox_db.session() as session:
        assert {e.node_id for e in events_of_kind(session, EventKind.NODE_OFFLINE)} == {"node-a", "node-b"}
    back = T0 + timedelta(hours=3)  # recommissioned, silent since T0: given offline_after_s to answer
    with outbox_db.write() as session:
        recommission_node(session, "node-c", now=back)
    assert check(outbox_db, back + timedelta(minutes=9)) == []
    assert check(outbox_db, back + timedelta(minutes=11)) == [EventKind.NODE_OFFLINE]
    with outbox_db.session() as session:
        offline, = [e for e in events_of_kind(session, EventKind.NODE_OFFLINE) if e.node_id == "node-c"]
    assert offline.payload["last_seen_at"] == T0.isoformat()  # the silence it reports is the real one
    assert offline.payload["offline_for_s"] == (back + timedelta(minutes=11) - T0).total_seconds()


def test_a_recommissioned_node_that_answers_within_offline_after_s_raises_no_alarm(outbox_db):
    from db.nodes import decommission_node, recommission_node

    with outbox_db.write() as session:
        decommission_node(session, "node-c", who="admin:ops", reason="cable repair", now=T0)
    back = T0 + timedelta(days=30)
    with outbox_db.write() as session:
        recommission_node(session, "node-c", now=back)
    # node-a and node-b, silent since T0 and watched all along, are offline; node-c not yet.
    assert check(outbox_db, back + timedelta(minutes=1)) == [EventKind.NODE_OFFLINE] * 2
    with outbox_db.write() as session:
        record_node_health(session, "node-c", online=True, seen_at=back + timedelta(minutes=5))
    assert check(outbox_db, back + timedelta(minutes=11)) == []  # it answered in time
    with outbox_db.session() as session:
        assert {e.node_id for e in events_of_kind(session, EventKind.NODE_OFFLINE)} == {"node-a", "node-b"}


def test_a_configured_node_that_never_answers_is_reported_offline_as_never_seen_and_online_at_its_first_answer(
    outbox_db,
):
    from db.nodes import register_configured_node, upsert_node
    from tests.support.db_fixtures import node_info

    started = T0 + timedelta(hours=1)  # the gateway restarts with node-d added to its configuration
    with outbox_db.write() as session:
        register_configured_node(session, "node-d", port_url="tcp://127.0.0.1:9", now=started)
    assert check(outbox_db, started + timedelta(minutes=9), watching_since=started) == []
    assert check(outbox_db, started + timedelta(minutes=11), watching_since=started) == [EventKind.NODE_OFFLINE] * 4
    assert check(outbox_db, started + timedelta(minutes=30), watching_since=started) == []
    with outbox_db.session() as session:
        never, = [e for e in events_of_kind(session, EventKind.NODE_OFFLINE) if e.node_id == "node-d"]
    assert never.payload["never_seen"] is True and never.payload["last_seen_at"] == started.isoformat()
    assert never.payload["offline_for_s"] == 660.0 and never.payload["state"] == "commissioning"
    restarted = started + timedelta(hours=1)  # still silent across a restart: the same outage, no new event
    assert check(outbox_db, restarted + timedelta(minutes=11), watching_since=restarted) == []
    answered = restarted + timedelta(minutes=20)
    with outbox_db.write() as session:
        upsert_node(session, node_info("node-d"), seen_at=answered)
    assert check(outbox_db, answered + timedelta(seconds=1), watching_since=restarted) == [EventKind.NODE_ONLINE]
    with outbox_db.session() as session:
        online, = events_of_kind(session, EventKind.NODE_ONLINE)
    assert online.payload["first_seen"] is True and online.payload["offline_event_id"] == str(never.id)
    assert online.payload["offline_for_s"] == (answered - started).total_seconds()


def test_a_node_never_seen_gets_offline_after_downtime_from_its_registration_or_the_gateways_start():
    from alerts.outages import offline_due, silent_since_of

    registered, seen = T0, T0 + timedelta(minutes=5)
    assert silent_since_of(None, registered) == registered and silent_since_of(seen, registered) == seen
    due = dict(offline_after_s=600.0)
    assert not offline_due(registered, T0, now=T0 + timedelta(seconds=600), **due)
    assert offline_due(registered, T0, now=T0 + timedelta(seconds=601), **due)
    restarted = T0 + timedelta(days=1)  # registered long ago, the gateway just started: it gets its time
    assert not offline_due(registered, restarted, now=restarted + timedelta(minutes=9), **due)


def test_every_new_baseline_gets_one_event_whoever_set_it(outbox_db):
    from alerts.baseline_watch import check_baseline_changes
    from db.baselines import set_active_baseline
    from db.models import MeasurementKind
    from tests.support.db_fixtures import store_sample

    with outbox_db.write() as session:
        first = store_sample(session, "node-a", kind=MeasurementKind.BASELINE, seed=1)
        second = store_sample(session, "node-a", kind=MeasurementKind.BASELINE, seed=2)
        set_active_baseline(session, "node-a", first.id, created_by="gateway", reason="commissioning", now=T0)
        set_active_baseline(session, "node-a", second.id, created_by="operator:alice", reason="pipe repaired",
                            now=T0 + timedelta(hours=1))
    now = T0 + timedelta(hours=2)
    with outbox_db.write() as session:
        added = check_baseline_changes(session, SETTINGS, now=now)
        assert check_baseline_changes(session, SETTINGS, now=now) == []  # one event per baseline row
    assert [e.kind for e in added] == [EventKind.BASELINE_CHANGED] * 2
    latest = added[-1].payload
    assert latest["measurement_id"] == second.id and latest["previous_measurement_id"] == first.id
    assert latest["created_by"] == "operator:alice" and latest["occurred_at"] == (T0 + timedelta(hours=1)).isoformat()
    with outbox_db.write() as session:  # a month later, old baselines are not looked at again
        assert check_baseline_changes(session, SETTINGS, now=T0 + timedelta(days=30)) == []


def test_a_node_whose_offline_alarm_ended_with_its_decommissioning_is_reported_again_if_still_silent(outbox_db):
    from alerts.alarms import decommissioning_events, open_alarms
    from db.measurements import add_event_once
    from db.nodes import decommission_node, recommission_node

    assert check(outbox_db, T0 + timedelta(minutes=11)) == [EventKind.NODE_OFFLINE] * 3
    with outbox_db.write() as session:
        decommission_node(session, "node-c", who="admin:ops", reason="moved", now=T0 + timedelta(minutes=20))
        for end in decommissioning_events(SETTINGS, open_alarms(session, "node-c"), node_id="node-c", state="ok",
                                          decommissioned_at=T0 + timedelta(minutes=20), by="admin:ops", reason="moved"):
            add_event_once(session, end, node_id="node-c", now=T0 + timedelta(minutes=20))
        recommission_node(session, "node-c", now=T0 + timedelta(minutes=20))
    (again,) = check(outbox_db, T0 + timedelta(minutes=40))
    assert again == EventKind.NODE_OFFLINE  # a new alarm, not refused as the old one's id
    with outbox_db.session() as session:
        assert open_alarms(session, "node-c").offline is not None
    assert check(outbox_db, T0 + timedelta(minutes=41)) == []


def test_a_baseline_change_is_logged_as_routine_and_an_outage_as_a_warning(outbox_db, caplog):
    """baseline_changed used to be logged at WARNING like an outage (issue 16, item 9)."""
    import logging
    import threading

    from alerts.delivery import FleetWatcher
    from db.baselines import set_active_baseline
    from db.models import MeasurementKind
    from tests.support.db_fixtures import store_sample

    with outbox_db.write() as session:
        row = store_sample(session, "node-a", kind=MeasurementKind.BASELINE, seed=1)
        set_active_baseline(session, "node-a", row.id, created_by="gateway", reason="commissioning", now=T0)
    watcher = FleetWatcher(SETTINGS, outbox_db, stop=threading.Event(), clock=lambda: T0 + timedelta(minutes=11))
    watcher.watching_since = T0
    with caplog.at_level(logging.DEBUG, logger="pipesentry"):
        watcher.check_once()
    levels = {r.event_kind: r.levelno for r in caplog.records if hasattr(r, "event_kind")}
    assert levels[EventKind.BASELINE_CHANGED] == logging.INFO
    assert levels[EventKind.NODE_OFFLINE] == logging.WARNING
