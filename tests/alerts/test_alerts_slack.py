"""Slack-compatible incoming webhook: one readable line per event, with links, through retries."""
from __future__ import annotations

from dataclasses import replace

import pytest

from alerts.outbox import pending_heads
from alerts.slack import slack_text
from db.models import DeliveryStatus
from tests.support.alerts_fixtures import (
    alerting,
    dead_receiver,
    deliveries,
    fast_policy,
    put_events,
    put_state_events,
    sensor_fault_pair,
    sink_worker,
)
from tests.support.alerts_receivers import HANG, HttpReceiver, fail
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(60)


def test_each_event_becomes_one_readable_line_with_links(outbox_db, stop):
    receiver = HttpReceiver([fail(500), HANG])
    try:
        settings = alerting({"type": "slack", "name": "chat", "url": receiver.url + "/services/T/B/X", **fast_policy()})
        events = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage"), ("damage", "ok")])
        sink_worker(settings, "chat", outbox_db, stop).thread.start()
        wait_until(lambda: [d.status for d, _ in deliveries(outbox_db)] == [DeliveryStatus.DELIVERED] * 2, 20, 0.05,
                   what="both delivered")
        texts = [r.json()["text"] for r in receiver.accepted()]
        assert len(texts) == 2 and all("\n" not in t for t in texts)
        raised, cleared = texts
        assert raised.startswith(":rotating_light: DAMAGE on node node-a: DI 0.5 vs threshold 0.3 at 200 mm axial, 90 deg")
        assert "<http://127.0.0.1:8000/api/v1/measurements/1|measurement 1>" in raised
        assert "<http://127.0.0.1:8000/api/v1/measurements/1/di-maps/gateway.png|DI map>" in raised
        assert raised.endswith(f"event {str(events[0].id)[:8]}")
        assert cleared.startswith(":white_check_mark: cleared on node node-a: damage → ok")
        assert {r.path for r in receiver.requests} == {"/services/T/B/X"}
    finally:
        receiver.close()


def test_slack_markup_characters_in_text_are_escaped(outbox_db):
    settings = alerting({"type": "slack", "name": "chat", "url": "http://127.0.0.1:9/x"})
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    with outbox_db.session() as session:
        item, = pending_heads(session, "chat")
    odd = replace(item, payload={**item.payload, "summary": "a <b> & c"})
    assert slack_text(odd).startswith(":rotating_light: a &lt;b&gt; &amp; c |")


def test_a_sensor_fault_and_its_clearing_read_as_one_line_each(outbox_db, stop):
    receiver = HttpReceiver()
    try:
        settings = alerting({"type": "slack", "name": "chat", "url": receiver.url + "/hook", **fast_policy()})
        raised, _ = put_events(outbox_db, list(sensor_fault_pair(settings, "node-a", dead_receiver(5))))
        worker = sink_worker(settings, "chat", outbox_db, stop)
        worker.run_once()
        worker.run_once()
        fault, back = (r.json()["text"] for r in receiver.accepted())
        assert fault.startswith(":warning: node node-a receiver 5 (112 deg) faulty: no signal "
                                "(direct arrival at 3% of baseline) in 2 consecutive measurements")
        assert "<http://127.0.0.1:8000/api/v1/measurements/7|measurement 7>" in fault
        assert fault.endswith(f"event {str(raised.id)[:8]}")
        assert back.startswith(":white_check_mark: node node-a receiver 5 (112 deg) healthy again")
        assert "was no_signal since measurement 7" in back and "\n" not in fault + back
    finally:
        receiver.close()
