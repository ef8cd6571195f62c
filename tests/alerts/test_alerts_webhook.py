"""Webhook sink against a real HTTP receiver: signatures verify independently, retries, order, 410 Gone."""
from __future__ import annotations

import base64
import json
from datetime import timedelta

import pytest
from standardwebhooks.webhooks import Webhook

from alerts.events import EventKind
from alerts.outbox import dead_count, delivery_counts, pending_count
from db.clock import utc_now
from db.models import DeliveryStatus
from tests.support.alerts_fixtures import (
    NODES,
    alerting,
    dead_receiver,
    deliveries,
    fast_policy,
    put_events,
    put_state_events,
    sensor_fault_pair,
    sink_worker,
)
from tests.support.alerts_receivers import GONE, HANG, HttpReceiver, fail
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(60)
SECRET = "whsec_" + base64.b64encode(bytes(range(32))).decode()


def webhook_sink(name: str, url: str, **policy) -> dict:
    return {"type": "webhook", "name": name, "url": url, "secret": SECRET, **fast_policy(**policy)}


@pytest.fixture
def receiver():
    r = HttpReceiver([fail(503), fail(500), HANG, fail(429, **{"Retry-After": "0"}), fail(502)])
    yield r
    r.close()


def test_every_event_arrives_signed_and_in_order_per_node_despite_failures_and_a_timeout(outbox_db, receiver, stop):
    settings = alerting(webhook_sink("hook", receiver.url + "/in"))
    events = put_state_events(outbox_db, settings)
    worker = sink_worker(settings, "hook", outbox_db, stop)
    worker.thread.start()
    ids = {str(e.id) for e in events}
    receiver.wait_for(lambda rs: {r.headers["webhook-id"] for r in rs if r.status == 200} >= ids, 30,
                      "every event accepted")
    wait_until(lambda: all(d.status == DeliveryStatus.DELIVERED for d, _ in deliveries(outbox_db)), 10,
               0.05, what="every delivery marked delivered")

    verifier = Webhook(SECRET)
    for request in receiver.requests:  # the failed tries were signed too
        data = verifier.verify(request.body, request.headers)
        assert data["data"]["event_id"] == request.headers["webhook-id"]
        assert data["type"] == "pipesentry." + data["data"]["kind"]
    # Order per node: the node's requests (tries included) never go back to an earlier event.
    position = {str(e.id): i for i, e in enumerate(events)}
    for node in NODES:
        seen = [position[r.headers["webhook-id"]] for r in receiver.requests if r.json()["data"]["node_id"] == node]
        assert seen == sorted(seen), f"{node} events out of order: {seen}"
    rows = deliveries(outbox_db, "hook")
    assert sum(d.attempts for d, _ in rows) == len(receiver.requests) == len(events) + 5
    assert all(d.last_error is None for d, _ in rows)
    with outbox_db.session() as session:
        assert dead_count(session) == pending_count(session) == 0
        assert delivery_counts(session) == {("hook", DeliveryStatus.DELIVERED): len(events)}


def test_a_tampered_body_does_not_verify(outbox_db, stop):
    receiver = HttpReceiver()
    try:
        settings = alerting(webhook_sink("hook", receiver.url))
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
        sink_worker(settings, "hook", outbox_db, stop).run_once()
        request = receiver.accepted()[0]
        tampered = request.body.replace(b'"damage"', b'"ok"')
        with pytest.raises(Exception, match=r"(?i)signature"):
            Webhook(SECRET).verify(tampered, request.headers)
    finally:
        receiver.close()


def test_retry_after_from_the_receiver_is_honoured(outbox_db, stop):
    receiver = HttpReceiver([fail(429, **{"Retry-After": "120"})])
    try:
        settings = alerting(webhook_sink("hook", receiver.url))
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "suspected")])
        before = utc_now()
        sink_worker(settings, "hook", outbox_db, stop).run_once()
        (delivery, _), = deliveries(outbox_db)
        assert delivery.status == DeliveryStatus.PENDING and delivery.attempts == 1
        assert delivery.next_attempt_at >= before + timedelta(seconds=120)
        assert "HTTP 429" in delivery.last_error
    finally:
        receiver.close()


def test_a_delivery_is_dead_after_max_attempts_and_the_node_queue_moves_on(outbox_db, stop):
    receiver = HttpReceiver([fail(500)] * 3)
    try:
        settings = alerting(webhook_sink("hook", receiver.url, max_attempts=3))
        events = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "suspected"), ("suspected", "ok")])
        worker = sink_worker(settings, "hook", outbox_db, stop)
        worker.thread.start()
        wait_until(lambda: [d.status for d, _ in deliveries(outbox_db)] == [DeliveryStatus.DEAD, DeliveryStatus.DELIVERED],
                   20, 0.05, what="first dead after 3 tries, second delivered")
        first, _second = deliveries(outbox_db)
        assert first[0].attempts == 3 and "HTTP 500" in first[0].last_error
        assert [r.headers["webhook-id"] for r in receiver.requests] == [str(events[0].id)] * 3 + [str(events[1].id)]
        with outbox_db.session() as session:
            assert dead_count(session) == 1 and dead_count(session, "hook") == 1 and dead_count(session, "other") == 0
    finally:
        receiver.close()


def test_410_gone_disables_the_sink_tells_the_other_sinks_and_survives_a_restart(outbox_db, stop):
    gone, other = HttpReceiver([GONE]), HttpReceiver()
    try:
        settings = alerting(webhook_sink("gone", gone.url), webhook_sink("other", other.url))
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "suspected"), ("suspected", "ok")])
        sink_worker(settings, "gone", outbox_db, stop).run_once()
        assert len(gone.requests) == 1  # the second event was never tried
        rows = deliveries(outbox_db, "gone")
        assert [d.status for d, _ in rows] == [DeliveryStatus.DEAD, DeliveryStatus.DEAD]
        assert all("410" in d.last_error for d, _ in rows)
        disabled = [e for _, e in deliveries(outbox_db, "other") if e.kind == EventKind.SINK_DISABLED]
        assert len(disabled) == 1 and disabled[0].payload["sink"] == "gone"

        # A restarted worker (same endpoint) sends nothing; new deliveries die at once.
        put_state_events(outbox_db, settings, node_ids=("node-b",), cycle=[("ok", "damage")], start_measurement_id=50)
        sink_worker(settings, "gone", outbox_db, stop).run_once()
        assert len(gone.requests) == 1
        assert [d.status for d, _ in deliveries(outbox_db, "gone")] == [DeliveryStatus.DEAD] * 3

        # Reconfigured to another endpoint, the sink works again.
        fixed = alerting(webhook_sink("gone", other.url + "/new"), webhook_sink("other", other.url))
        put_state_events(outbox_db, fixed, node_ids=("node-c",), cycle=[("ok", "damage")], start_measurement_id=60)
        sink_worker(fixed, "gone", outbox_db, stop).run_once()
        assert [r.path for r in other.requests] == ["/new"]
        body = json.loads(other.requests[0].body)
        assert body["data"]["node_id"] == "node-c"
    finally:
        gone.close()
        other.close()


def test_a_sensor_fault_and_its_clearing_arrive_signed_with_the_receiver_and_a_pointer_back(outbox_db, stop):
    receiver = HttpReceiver()
    try:
        settings = alerting(webhook_sink("hook", receiver.url))
        raised, cleared = put_events(outbox_db, list(sensor_fault_pair(settings, "node-b", dead_receiver(3, "amplitude"))))
        worker = sink_worker(settings, "hook", outbox_db, stop)
        worker.run_once()
        worker.run_once()
        first, second = (Webhook(SECRET).verify(r.body, r.headers) for r in receiver.accepted())
        assert [r.headers["webhook-id"] for r in receiver.accepted()] == [str(raised.id), str(cleared.id)]
        assert first["type"] == "pipesentry.sensor_fault" and second["type"] == "pipesentry.sensor_fault_cleared"
        data = first["data"]
        assert data["node_id"] == "node-b" and data["severity"] == "warning" and data["measurement_id"] == 7
        assert data["receiver"] == {"rx_index": 3, "rx_angle_deg": 67.5, "kind": "amplitude",
                                    "amplitude_ratio": 0.03, "delay_s": 0.0}
        assert data["faulty_receivers"] == [3] and data["links"]["measurement"].endswith("/api/v1/measurements/7")
        assert second["data"]["raised_event_id"] == str(raised.id) and second["data"]["receiver"] == data["receiver"]
        assert second["data"]["faulty_receivers"] == [] and second["data"]["routing_severity"] == "warning"
    finally:
        receiver.close()
