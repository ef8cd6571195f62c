"""Alertmanager sink against a stand-in that validates every POST against the v2 postableAlerts schema."""
from __future__ import annotations

from datetime import datetime

import pytest

from alerts.alertmanager import OFFLINE_ALERT, SENSOR_FAULT_ALERT, AlertmanagerTransport
from alerts.delivery import SinkWorker
from alerts.events import node_offline_event, node_online_event
from db.measurements import add_event
from db.models import DeliveryStatus
from tests.support.alerts_fixtures import (
    T0,
    alerting,
    dead_receiver,
    deliveries,
    fast_policy,
    put_events,
    put_state_events,
    sensor_fault_pair,
    sink_worker,
)
from tests.support.alerts_receivers import HANG, alertmanager_receiver, fail
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(60)


def am_sink(url: str, **policy) -> dict:
    return {"type": "alertmanager", "name": "am", "url": url, "resend_interval_s": 3600, **fast_policy(**policy)}


class Monotonic:
    """A monotonic clock the test moves forward by hand (the re-send interval passing)."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def worker_with_clock(settings, database, stop, clock: Monotonic) -> SinkWorker:
    sink = settings.sink("am")
    return SinkWorker(settings, sink, AlertmanagerTransport(sink, database, monotonic=clock), database, stop=stop)


def when(text: str) -> datetime:
    return datetime.fromisoformat(text)


def by_alert(alerts: list[dict]) -> dict[tuple[str, str], dict]:
    return {(a["labels"]["alertname"], a["labels"].get("state", "")): a for a in alerts}


@pytest.fixture
def am():
    receiver = alertmanager_receiver([fail(503), HANG])
    yield receiver
    receiver.close()


def test_raise_escalate_clear_reach_alertmanager_as_valid_alerts_with_end_times(outbox_db, am, stop):
    settings = alerting(am_sink(am.url))
    events = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "suspected"), ("suspected", "damage"), ("damage", "ok")])
    worker = sink_worker(settings, "am", outbox_db, stop)
    worker.thread.start()
    accepted = am.wait_for(lambda rs: sum(r.status == 200 for r in rs) >= 3, 30, "3 events accepted")
    assert am.invalid == []
    posts = [r.json() for r in accepted if r.status == 200]
    ids = [[a["annotations"]["event_id"] for a in post] for post in posts[:3]]
    assert all(set(i) == {str(e.id)} for i, e in zip(ids, events, strict=True))

    suspected = by_alert(posts[0])
    assert suspected["PipeSentryPipeDamage", "suspected"]["labels"] == {
        "alertname": "PipeSentryPipeDamage", "node": "node-a", "severity": "warning", "state": "suspected"}
    firing = suspected["PipeSentryPipeDamage", "suspected"]
    assert when(firing["endsAt"]) > when(firing["startsAt"])  # active: ends only if not re-sent
    assert firing["annotations"]["location"] == "200 mm axial, 90 deg"
    assert firing["annotations"]["di"] == "DI 0.5 vs threshold 0.3"
    assert firing["generatorURL"].endswith("/api/v1/measurements/1")
    assert firing["annotations"]["di_map_png_url"].endswith("/api/v1/measurements/1/di-maps/gateway.png")

    escalated = by_alert(posts[1])
    assert escalated["PipeSentryPipeDamage", "damage"]["labels"]["severity"] == "critical"
    ended = escalated["PipeSentryPipeDamage", "suspected"]
    assert when(ended["endsAt"]) == when(ended["startsAt"])  # the warning is resolved as the critical fires

    cleared = by_alert(posts[2])
    assert all(when(a["endsAt"]) <= when(a["startsAt"]) for a in cleared.values()), "clearing ends every state alert"
    wait_until(lambda: [d.status for d, _ in deliveries(outbox_db)] == [DeliveryStatus.DELIVERED] * 3, 10, 0.05,
               what="all three marked delivered")


def test_active_alerts_are_re_sent_and_stop_being_re_sent_once_cleared(outbox_db, stop):
    am = alertmanager_receiver()
    try:
        settings = alerting(am_sink(am.url))
        clock = Monotonic()
        worker = worker_with_clock(settings, outbox_db, stop, clock)
        put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"), cycle=[("ok", "damage")])
        worker.run_once()  # delivers both
        sent = len(am.requests)
        worker.run_once()
        assert len(am.requests) == sent, "nothing is re-sent before the interval has passed"
        clock.now_s += 3600
        worker.run_once()
        assert am.invalid == []
        resend = am.requests[-1].json()
        assert sorted((a["labels"]["node"], a["labels"]["severity"]) for a in resend) == [
            ("node-a", "critical"), ("node-b", "critical")]
        assert all(when(a["endsAt"]) > when(a["startsAt"]) for a in resend)

        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("damage", "ok")], start_measurement_id=10)
        worker.run_once()
        clock.now_s += 3600
        worker.run_once()
        assert [a["labels"]["node"] for a in am.requests[-1].json()] == ["node-b"]
    finally:
        am.close()


def test_a_decommissioned_nodes_alerts_are_no_longer_re_sent_until_it_is_back_in_service(outbox_db, stop):
    from db.nodes import decommission_node, recommission_node

    am = alertmanager_receiver()
    try:
        settings = alerting(am_sink(am.url))
        clock = Monotonic()
        worker = worker_with_clock(settings, outbox_db, stop, clock)
        put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"), cycle=[("ok", "damage")])
        worker.run_once()
        with outbox_db.write() as session:
            decommission_node(session, "node-b", who="admin:ops", reason="line removed")
        clock.now_s += 3600
        worker.run_once()
        assert [a["labels"]["node"] for a in am.requests[-1].json()] == ["node-a"]
        with outbox_db.write() as session:
            recommission_node(session, "node-b")
        clock.now_s += 3600
        worker.run_once()
        assert sorted(a["labels"]["node"] for a in am.requests[-1].json()) == ["node-a", "node-b"]
        assert am.invalid == []
    finally:
        am.close()


def test_node_offline_fires_and_node_online_ends_the_offline_alert(outbox_db, stop):
    am = alertmanager_receiver()
    try:
        settings = alerting(am_sink(am.url))
        offline = node_offline_event(settings, node_id="node-c", state="ok", last_seen_at=T0, now=T0.replace(hour=13))
        online = node_online_event(settings, node_id="node-c", state="ok", offline_event_id=offline.id,
                                   offline_since=T0, seen_at=T0.replace(hour=14))
        for event in (offline, online):
            with outbox_db.write() as session:
                add_event(session, event, node_id="node-c")
        worker = sink_worker(settings, "am", outbox_db, stop)
        worker.run_once()  # sends node_offline, then re-sends it as the active alert
        worker.run_once()  # sends node_online
        assert am.invalid == [] and len(am.requests) == 3
        fired, resent, ended = (r.json()[0] for r in am.requests)
        assert resent["labels"] == fired["labels"]
        assert fired["labels"] == ended["labels"] == {"alertname": OFFLINE_ALERT, "node": "node-c", "severity": "warning"}
        assert when(fired["endsAt"]) > when(fired["startsAt"]) and when(ended["endsAt"]) == when(ended["startsAt"])
    finally:
        am.close()


def test_going_blind_keeps_the_damage_alert_firing(outbox_db, stop):
    am = alertmanager_receiver()
    try:
        settings = alerting(am_sink(am.url))
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage"), ("damage", "no_valid_baseline")])
        clock = Monotonic()
        worker = worker_with_clock(settings, outbox_db, stop, clock)
        worker.run_once()
        worker.run_once()
        clock.now_s += 3600
        worker.run_once()
        assert am.invalid == []
        resend = by_alert(am.requests[-1].json())
        assert set(resend) == {("PipeSentryPipeDamage", "damage"), ("PipeSentryMonitoringBlind", "no_valid_baseline")}
    finally:
        am.close()


def test_a_sensor_fault_fires_per_receiver_is_re_sent_and_its_clearing_resolves_the_same_labels(outbox_db, stop):
    am = alertmanager_receiver()
    try:
        settings = alerting(am_sink(am.url))
        clock = Monotonic()
        worker = worker_with_clock(settings, outbox_db, stop, clock)
        rx5_raised, rx5_cleared = sensor_fault_pair(settings, "node-a", dead_receiver(5))
        rx2_raised, _ = sensor_fault_pair(settings, "node-a", dead_receiver(2, kind="timing"), measurement_id=8)
        put_events(outbox_db, [rx5_raised, rx2_raised])
        put_state_events(outbox_db, settings, node_ids=("node-b",), cycle=[("ok", "damage")])
        worker.run_once()  # the first event of each node, then the re-send of what is active
        worker.run_once()  # node-a's second fault
        assert am.invalid == []
        fired = am.requests[0].json()[0]
        assert fired["labels"] == {"alertname": SENSOR_FAULT_ALERT, "node": "node-a", "rx_index": "5",
                                   "kind": "no_signal", "severity": "warning"}
        assert when(fired["endsAt"]) > when(fired["startsAt"])
        assert fired["annotations"]["event_id"] == str(rx5_raised.id)
        assert fired["annotations"]["receiver"] == "no signal (direct arrival at 3% of baseline)"
        assert fired["generatorURL"].endswith("/api/v1/measurements/7") and "di" not in fired["annotations"]

        clock.now_s += 3600
        worker.run_once()
        resend = am.requests[-1].json()
        assert sorted((a["labels"]["alertname"], a["labels"]["node"], a["labels"].get("rx_index", "")) for a in resend) == [
            ("PipeSentryPipeDamage", "node-b", ""), (SENSOR_FAULT_ALERT, "node-a", "2"), (SENSOR_FAULT_ALERT, "node-a", "5")]
        assert all(when(a["endsAt"]) > when(a["startsAt"]) for a in resend)

        put_events(outbox_db, [rx5_cleared])
        worker.run_once()
        ended = am.requests[-1].json()
        assert len(ended) == 1 and ended[0]["labels"] == fired["labels"]
        assert when(ended[0]["endsAt"]) == when(ended[0]["startsAt"]) and ended[0]["annotations"]["event_id"] == str(rx5_cleared.id)
        clock.now_s += 3600
        worker.run_once()
        assert am.invalid == []
        assert sorted(a["labels"].get("rx_index", "-") for a in am.requests[-1].json()) == ["-", "2"], \
            "the cleared receiver is no longer re-sent, the other one still is"
    finally:
        am.close()
