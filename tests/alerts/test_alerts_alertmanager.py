"""Alertmanager sink against a stand-in that validates every POST against the v2 postableAlerts schema."""
from __future__ import annotations

from datetime import datetime, timedelta

import pytest

from alerts.alarms import BaselineSet, alarm_change, alarm_events, open_alarms
from alerts.alertmanager import OFFLINE_ALERT, SENSOR_FAULT_ALERT, AlertmanagerTransport, rfc3339
from alerts.delivery import SinkWorker
from alerts.events import node_offline_event, node_online_event
from db.measurements import add_event
from db.models import DeliveryStatus, NodeRow, NodeState
from db.records import DetectionInput
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
from tests.support.db_fixtures import store_sample
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
    """An Alertmanager stand-in that answers 503 first, then hangs once."""
    receiver = alertmanager_receiver([fail(503), HANG])
    yield receiver
    receiver.close()


@pytest.fixture
def am_ok():
    """An Alertmanager stand-in that accepts every valid POST."""
    receiver = alertmanager_receiver()
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


def test_active_alerts_are_re_sent_and_stop_being_re_sent_once_cleared(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"), cycle=[("ok", "damage")])
    worker.run_once()  # delivers both
    sent = len(am_ok.requests)
    worker.run_once()
    assert len(am_ok.requests) == sent, "nothing is re-sent before the interval has passed"
    clock.now_s += 3600
    worker.run_once()
    assert am_ok.invalid == []
    resend = am_ok.requests[-1].json()
    assert sorted((a["labels"]["node"], a["labels"]["severity"]) for a in resend) == [
        ("node-a", "critical"), ("node-b", "critical")]
    assert all(when(a["endsAt"]) > when(a["startsAt"]) for a in resend)

    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("damage", "ok")], start_measurement_id=10)
    worker.run_once()
    clock.now_s += 3600
    worker.run_once()
    assert [a["labels"]["node"] for a in am_ok.requests[-1].json()] == ["node-b"]


def test_a_decommissioned_nodes_alerts_are_no_longer_re_sent_until_it_is_back_in_service(outbox_db, stop, am_ok):
    from db.nodes import decommission_node, recommission_node

    settings = alerting(am_sink(am_ok.url))
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"), cycle=[("ok", "damage")])
    worker.run_once()
    with outbox_db.write() as session:
        decommission_node(session, "node-b", who="admin:ops", reason="line removed")
    clock.now_s += 3600
    worker.run_once()
    assert [a["labels"]["node"] for a in am_ok.requests[-1].json()] == ["node-a"]
    with outbox_db.write() as session:
        recommission_node(session, "node-b")
    clock.now_s += 3600
    worker.run_once()
    assert sorted(a["labels"]["node"] for a in am_ok.requests[-1].json()) == ["node-a", "node-b"]
    assert am_ok.invalid == []


def test_node_offline_fires_and_node_online_ends_the_offline_alert(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    offline = node_offline_event(settings, node_id="node-c", state="ok", last_seen_at=T0, now=T0.replace(hour=13))
    online = node_online_event(settings, node_id="node-c", state="ok", offline_event_id=offline.id,
                               offline_since=T0, seen_at=T0.replace(hour=14))
    for event in (offline, online):
        with outbox_db.write() as session:
            add_event(session, event, node_id="node-c")
    worker = sink_worker(settings, "am", outbox_db, stop)
    worker.run_once()  # sends node_offline, then re-sends it as the active alert
    worker.run_once()  # sends node_online
    assert am_ok.invalid == [] and len(am_ok.requests) == 3
    fired, resent, ended = (r.json()[0] for r in am_ok.requests)
    assert resent["labels"] == fired["labels"]
    assert fired["labels"] == ended["labels"] == {"alertname": OFFLINE_ALERT, "node": "node-c", "severity": "warning"}
    assert when(fired["endsAt"]) > when(fired["startsAt"]) and when(ended["endsAt"]) == when(ended["startsAt"])


def test_going_blind_keeps_the_damage_alert_firing(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage"), ("damage", "no_valid_baseline")])
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    worker.run_once()
    worker.run_once()
    clock.now_s += 3600
    worker.run_once()
    assert am_ok.invalid == []
    resend = by_alert(am_ok.requests[-1].json())
    assert set(resend) == {("PipeSentryPipeDamage", "damage"), ("PipeSentryMonitoringBlind", "no_valid_baseline")}


def test_a_sensor_fault_fires_per_receiver_is_re_sent_and_its_clearing_resolves_the_same_labels(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    rx5_raised, rx5_cleared = sensor_fault_pair(settings, "node-a", dead_receiver(5))
    rx2_raised, _ = sensor_fault_pair(settings, "node-a", dead_receiver(2, kind="timing"), measurement_id=8)
    put_events(outbox_db, [rx5_raised, rx2_raised])
    put_state_events(outbox_db, settings, node_ids=("node-b",), cycle=[("ok", "damage")])
    worker.run_once()  # the first event of each node, then the re-send of what is active
    worker.run_once()  # node-a's second fault
    assert am_ok.invalid == []
    fired = am_ok.requests[0].json()[0]
    assert fired["labels"] == {"alertname": SENSOR_FAULT_ALERT, "node": "node-a", "rx_index": "5",
                               "kind": "no_signal", "severity": "warning"}
    assert when(fired["endsAt"]) > when(fired["startsAt"])
    assert fired["annotations"]["event_id"] == str(rx5_raised.id)
    assert fired["annotations"]["receiver"] == "no signal (direct arrival at 3% of baseline)"
    assert fired["generatorURL"].endswith("/api/v1/measurements/7") and "di" not in fired["annotations"]

    clock.now_s += 3600
    worker.run_once()
    resend = am_ok.requests[-1].json()
    assert sorted((a["labels"]["alertname"], a["labels"]["node"], a["labels"].get("rx_index", "")) for a in resend) == [
        ("PipeSentryPipeDamage", "node-b", ""), (SENSOR_FAULT_ALERT, "node-a", "2"), (SENSOR_FAULT_ALERT, "node-a", "5")]
    assert all(when(a["endsAt"]) > when(a["startsAt"]) for a in resend)

    put_events(outbox_db, [rx5_cleared])
    worker.run_once()
    ended = am_ok.requests[-1].json()
    assert len(ended) == 1 and ended[0]["labels"] == fired["labels"]
    assert when(ended[0]["endsAt"]) == when(ended[0]["startsAt"]) and ended[0]["annotations"]["event_id"] == str(rx5_cleared.id)
    clock.now_s += 3600
    worker.run_once()
    assert am_ok.invalid == []
    assert sorted(a["labels"].get("rx_index", "-") for a in am_ok.requests[-1].json()) == ["-", "2"], \
        "the cleared receiver is no longer re-sent, the other one still is"


def test_a_re_send_carries_the_current_di_estimate_and_map_not_those_of_the_raise(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    (raised,) = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    worker.run_once()
    # The defect grows: a later reading of the same node, DI 0.61 at 1830 mm / 97 deg.
    grown = DetectionInput(peak_di=0.61, threshold=0.3, state=NodeState.DAMAGE, axial_mm=1830.0, angle_deg=97.0)
    with outbox_db.write() as session:
        later = store_sample(session, "node-a", detection=grown)
    clock.now_s += 3600
    worker.run_once()
    assert am_ok.invalid == []
    (resent,) = am_ok.requests[-1].json()
    notes = resent["annotations"]
    assert notes["di"] == "DI 0.61 vs threshold 0.3" and notes["location"] == "1830 mm axial, 97 deg"
    assert notes["measurement_url"].endswith(f"/api/v1/measurements/{later.id}")
    assert resent["generatorURL"].endswith(f"/api/v1/measurements/{later.id}")
    assert "DI 0.61" in notes["summary"] and notes["event_id"] == str(raised.id)
    assert resent["startsAt"] == rfc3339(T0)  # still the alarm that began at the raise


def test_an_offline_alert_carries_no_di_or_location(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    put_events(outbox_db, [node_offline_event(settings, node_id="node-c", state="ok", last_seen_at=T0,
                                              now=T0.replace(hour=13))])
    sink_worker(settings, "am", outbox_db, stop).run_once()
    for request in am_ok.requests:
        (alert,) = request.json()
        assert alert["labels"]["alertname"] == OFFLINE_ALERT
        assert not {"di", "location"} & set(alert["annotations"]), alert["annotations"]
        assert alert["annotations"]["node_url"].endswith("/api/v1/nodes/node-c")


def test_a_damage_alarm_ended_by_a_new_baseline_resolves_both_severities_and_is_no_longer_re_sent(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url))
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    (raised,) = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    worker.run_once()
    with outbox_db.write() as session:
        session.get(NodeRow, "node-a").state = NodeState.CALIBRATING
        alarms = open_alarms(session, "node-a")
        baseline = BaselineSet(9, T0 + timedelta(hours=1), "alice", "clamp repaired")
        change = alarm_change(alarms, state="calibrating", baseline=baseline)
        (cleared,) = alarm_events(settings, change, alarms, node_id="node-a", from_state="damage",
                                  to_state="calibrating", measurement_id=30, peak_di=0.01, threshold=None,
                                  axial_mm=None, angle_deg=None, reason=None, occurred_at=T0 + timedelta(hours=2))
        add_event(session, cleared, node_id="node-a")
    worker.run_once()
    ended = am_ok.requests[-1].json()
    assert sorted(a["labels"]["severity"] for a in ended) == ["critical", "warning"]
    assert all(a["endsAt"] == rfc3339(T0 + timedelta(hours=2)) for a in ended)
    assert ended[0]["annotations"]["ended_by"] == "rebaseline"
    assert ended[0]["annotations"]["alarm_id"] == str(raised.id)
    sent = len(am_ok.requests)
    clock.now_s += 3600
    worker.run_once()
    assert len(am_ok.requests) == sent, "nothing active is left to re-send"


def test_labels_from_the_sink_settings_are_added_to_every_alert(outbox_db, stop, am_ok):
    settings = alerting(am_sink(am_ok.url, labels={"site": "north-7"}))
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "suspected")])
    sink_worker(settings, "am", outbox_db, stop).run_once()
    assert am_ok.invalid == [] and am_ok.requests
    assert all(a["labels"]["site"] == "north-7" for r in am_ok.requests for a in r.json())


@pytest.mark.parametrize("labels, why", [({"node": "x"}, "set by PipeSentry"), ({"bad-name": "x"}, "label name")])
def test_sink_labels_that_would_replace_an_alerts_own_or_are_no_label_names_are_refused(labels, why):
    with pytest.raises(ValueError, match=why):
        alerting(am_sink("http://127.0.0.1:9093", labels=labels))


def test_an_alarm_of_an_older_release_that_never_heard_its_end_is_not_re_sent_once_the_node_is_sound(outbox_db, stop, am_ok):
    # Schema 1 ended a damage alarm open through a blind spell with monitoring_restored only.
    settings = alerting(am_sink(am_ok.url))
    put_state_events(outbox_db, settings, node_ids=("node-a",),
                     cycle=[("ok", "damage"), ("damage", "no_valid_baseline"), ("no_valid_baseline", "ok")])
    clock = Monotonic()
    worker = worker_with_clock(settings, outbox_db, stop, clock)
    for _ in range(3):
        worker.run_once()
    sent = len(am_ok.requests)
    clock.now_s += 3600
    worker.run_once()
    assert len(am_ok.requests) == sent, "the node reads ok: nothing of it is active"
