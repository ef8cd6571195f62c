"""The delivery worker as a whole: a dead sink blocks nobody, kill -9 loses nothing, counts for the API."""
from __future__ import annotations

import base64
import os
import signal
import subprocess
import sys
from datetime import timedelta

import pytest
from standardwebhooks.webhooks import Webhook

from alerts.delivery import AlertDelivery
from alerts.outbox import delivery_counts, oldest_pending_age_s, pending_count
from db.clock import utc_now
from db.models import DeliveryStatus
from tests.support.alerts_fixtures import alerting, deliveries, fast_policy, put_state_events
from tests.support.alerts_receivers import HANG, HttpReceiver
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(90)
SECRET = "whsec_" + base64.b64encode(b"s" * 32).decode()


def hook(name: str, url: str, **policy) -> dict:
    return {"type": "webhook", "name": name, "url": url, "secret": SECRET, **fast_policy(**policy)}


def statuses(database, sink: str) -> list[DeliveryStatus]:
    return [d.status for d, _ in deliveries(database, sink)]


def test_a_sink_that_hangs_blocks_neither_the_other_sinks_nor_writers_and_ends_dead(outbox_db, stop):
    down, up = HttpReceiver([HANG] * 100), HttpReceiver()
    try:
        settings = alerting(hook("down", down.url, timeout_s=0.2, max_attempts=2), hook("up", up.url))
        events = put_state_events(outbox_db, settings)
        delivery = AlertDelivery(settings, outbox_db, stop=stop, watch_fleet=False)
        delivery.start()
        wait_until(lambda: statuses(outbox_db, "up") == [DeliveryStatus.DELIVERED] * len(events), 20, 0.05,
                   what="the healthy sink has everything")
        assert DeliveryStatus.PENDING in statuses(outbox_db, "down"), "the hanging sink is still trying"
        more = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("suspected", "ok")],
                                start_measurement_id=100)  # writers are not held up either
        wait_until(lambda: statuses(outbox_db, "up") == [DeliveryStatus.DELIVERED] * (len(events) + len(more)), 20,
                   0.05, what="a later event reaches the healthy sink")
        wait_until(lambda: statuses(outbox_db, "down") == [DeliveryStatus.DEAD] * (len(events) + len(more)), 40, 0.1,
                   what="every delivery to the hanging sink dead")
        rows = deliveries(outbox_db, "down")
        assert all(d.attempts == 2 and "timed out" in d.last_error for d, _ in rows)
        with outbox_db.session() as session:
            counts = delivery_counts(session)
        assert counts == {("up", DeliveryStatus.DELIVERED): 13, ("down", DeliveryStatus.DEAD): 13}
        stop.set()
        delivery.join(5)
        assert not any(t.is_alive() for t in delivery.threads)
    finally:
        down.close()
        up.close()


def test_oldest_pending_age_and_pending_count_per_sink(outbox_db):
    settings = alerting(hook("a", "http://127.0.0.1:9/"), hook("b", "http://127.0.0.1:9/"))
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    later = utc_now() + timedelta(seconds=100)
    with outbox_db.session() as session:
        ages = oldest_pending_age_s(session, now=later)
        assert set(ages) == {"a", "b"} and all(99 < age < 200 for age in ages.values())
        assert pending_count(session) == 2 and pending_count(session, "a") == 1


def start_delivery_process(config_path, log_path) -> subprocess.Popen:
    with open(log_path, "ab") as log:  # the child keeps its own copy of the descriptor
        return subprocess.Popen([sys.executable, "-m", "alerts", "deliver", "--config", str(config_path)],
                                stdout=log, stderr=log, stdin=subprocess.DEVNULL, start_new_session=True)


@pytest.mark.e2e
def test_kill_9_during_a_send_and_restart_delivers_everything(tmp_path, outbox_db):
    receiver = HttpReceiver([HANG])
    db_path = tmp_path / "alerts.db"
    config = tmp_path / "gateway.toml"
    config.write_text(f"""
[database]
url = "sqlite:///{db_path}"
[alerting]
poll_interval_s = 0.05
[[alerting.sinks]]
type = "webhook"
name = "hook"
url = "{receiver.url}"
secret = "{SECRET}"
timeout_s = 1.0
backoff_base_s = 0.01
backoff_cap_s = 0.05
[[nodes]]
id = "unused"
url = "loop://"
""")
    settings = alerting(hook("hook", receiver.url))
    events = put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"), cycle=[("ok", "damage")])
    first = start_delivery_process(config, tmp_path / "deliver.log")
    second = None
    try:
        receiver.wait_for(lambda rs: len(rs) >= 1, 30, "the first send to be in flight")
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        in_flight = [d for d, _ in deliveries(outbox_db) if d.attempts == 1 and d.status == DeliveryStatus.PENDING]
        assert len(in_flight) == 1, "the claim was committed before the send"
        late = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("damage", "ok")],
                                start_measurement_id=10)  # created while nothing is delivering

        second = start_delivery_process(config, tmp_path / "deliver.log")
        wanted = {str(e.id) for e in events + late}
        receiver.wait_for(lambda rs: {r.headers["webhook-id"] for r in rs if r.status == 200} >= wanted, 30,
                          "every event accepted after the restart")
        wait_until(lambda: statuses(outbox_db, "hook") == [DeliveryStatus.DELIVERED] * 3, 10, 0.05,
                   what="all marked delivered")
        hung_id = receiver.requests[0].headers["webhook-id"]
        assert [r.headers["webhook-id"] for r in receiver.requests].count(hung_id) == 2  # at least once: sent again
        for request in receiver.requests:
            Webhook(SECRET).verify(request.body, request.headers)
        second.send_signal(signal.SIGTERM)
        assert second.wait(10) == 0
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)
        receiver.close()
