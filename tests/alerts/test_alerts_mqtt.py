"""MQTT sink against the real Mosquitto broker on 127.0.0.1:1883: the retained current state per node, the event
stream, the gateway's status and last will; PUBACK awaited."""
from __future__ import annotations

import json
import socket
import threading
import uuid

import pytest

from alerts.delivery import SinkWorker
from alerts.errors import DeliveryFailed
from alerts.events import baseline_changed_event
from alerts.mqtt import MqttTransport
from alerts.outbox import pending_heads
from db.database import open_database
from db.models import DeliveryStatus, NodeRow, NodeState
from db.nodes import upsert_node
from db.records import DetectionInput, StateChangeInput
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
from tests.support.db_fixtures import node_info, store_sample
from tests.support.mqtt_broker import BROKER, Subscriber, clear_retained
from tests.support.process_harness import PYTHON, Proc, wait_until

pytestmark = pytest.mark.timeout(60)
CALIBRATING = DetectionInput(peak_di=0.012, threshold=None, state=NodeState.CALIBRATING)
SOUND = DetectionInput(peak_di=0.01, threshold=0.02, state=NodeState.OK, axial_mm=210.0, angle_deg=80.0)


class Monotonic:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s
def mqtt_sink(prefix: str, **policy) -> dict:
    return {"type": "mqtt", "name": "scada", "host": BROKER[0], "port": BROKER[1], "topic_prefix": prefix,
            "gateway_topic": prefix.replace("/nodes", "/gateway"), "state_interval_s": 0.05, **fast_policy(**policy)}


def unique_prefix() -> str:
    return f"pstest-{uuid.uuid4().hex[:8]}/nodes"


def retained_now(topic_filter: str, count: int) -> dict[str, dict]:
    """What a subscriber connecting now gets at once: {topic: document} of the retained messages."""
    late = Subscriber(topic_filter)
    try:
        messages = late.wait_for(count)
    finally:
        late.close()
    assert all(m.retain for m in messages)
    return {m.topic: json.loads(m.payload) for m in messages}


def test_each_node_event_is_published_on_its_event_stream_with_qos_1_in_order(broker, outbox_db, stop):
    prefix = unique_prefix()
    live = Subscriber(f"{prefix}/+/events")
    try:
        settings = alerting(mqtt_sink(prefix))
        events = put_state_events(outbox_db, settings, node_ids=("node-a", "node-b"))
        worker = sink_worker(settings, "scada", outbox_db, stop)
        worker.thread.start()
        wait_until(lambda: all(d.status == DeliveryStatus.DELIVERED for d, _ in deliveries(outbox_db)), 20, 0.05,
                   what="all published")
        received = live.wait_for(len(events))
        for node_id in ("node-a", "node-b"):
            sent = [str(e.id) for e in events if e.payload["node_id"] == node_id]
            got = [json.loads(m.payload)["event_id"] for m in received if m.topic == f"{prefix}/{node_id}/events"]
            assert got == sent
        assert all(m.qos == 1 and not m.retain for m in received)
        last = json.loads(received[-1].payload)
        assert last["kind"] == "damage_raised" and last["links"]["di_map_png"].endswith("/di-maps/gateway.png")
        assert last["location"] == {"axial_mm": 200.0, "angle_deg": 90.0} and last["schema"] == 2
    finally:
        live.close()
        clear_retained(*(f"{prefix}/{n}/state" for n in NODES), f"{prefix.replace('/nodes', '/gateway')}/status")


def test_the_retained_state_is_the_nodes_current_state_not_its_last_event(broker, outbox_db, stop):
    # The issue: a healthy node showed "baseline_changed, calibrating" for its whole healthy period.
    prefix = unique_prefix()
    topic = f"{prefix}/node-a/state"
    settings = alerting(mqtt_sink(prefix))
    sink = settings.sink("scada")
    clock = Monotonic()  # the state documents are synced at most every state_interval_s of this clock
    worker = SinkWorker(settings, sink, MqttTransport(sink, settings, outbox_db, monotonic=clock), outbox_db, stop=stop)

    def deliver_later() -> None:
        clock.now_s += 1.0
        worker.run_once()

    try:
        with outbox_db.write() as session:
            store_sample(session, "node-a", detection=CALIBRATING,
                         state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.CALIBRATING))
        put_events(outbox_db, [baseline_changed_event(settings, node_id="node-a", baseline_id=1, measurement_id=1,
                                                      previous_measurement_id=None, created_by="gateway",
                                                      reason="commissioning", state="calibrating")])
        deliver_later()
        assert retained_now(topic, 1)[topic]["state"] == "calibrating"
        # calibrating -> ok raises no event; the retained state follows all the same
        with outbox_db.write() as session:
            sound = store_sample(session, "node-a", detection=SOUND,
                                 state_change=StateChangeInput(NodeState.CALIBRATING, NodeState.OK))
        deliver_later()
        state = retained_now(topic, 1)[topic]
        assert state["state"] == "ok" and state["online"] is True and state["alarms"] == []
        assert state["latest"]["measurement_id"] == sound.id and state["latest"]["detection"]["peak_di"] == 0.01
        assert "kind" not in state and "event_id" not in state  # a state, not an event
        # damage raised: the state shows the open alarm; its end removes it
        (raised,) = put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
        deliver_later()
        deliver_later()
        state = retained_now(topic, 1)[topic]
        assert state["state"] == "damage"
        assert [(a["alarm"], a["severity"], a["alarm_id"]) for a in state["alarms"]] == [
            ("damage", "critical", str(raised.id))]
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("damage", "ok")], start_measurement_id=9)
        deliver_later()
        deliver_later()
        state = retained_now(topic, 1)[topic]
        assert state["state"] == "ok" and state["alarms"] == []
    finally:
        worker.transport.close()
        clear_retained(topic, f"{prefix.replace('/nodes', '/gateway')}/status")


def test_the_state_is_published_only_when_it_changes(broker, outbox_db, stop):
    prefix = unique_prefix()
    live = Subscriber(f"{prefix}/node-a/state")
    settings = alerting(mqtt_sink(prefix))
    sink = settings.sink("scada")
    clock = Monotonic()
    worker = SinkWorker(settings, sink, MqttTransport(sink, settings, outbox_db, monotonic=clock), outbox_db, stop=stop)
    try:
        for _ in range(5):
            worker.run_once()
            clock.now_s += 1.0  # past state_interval_s: each pass looks again
        with outbox_db.write() as session:
            session.get(NodeRow, "node-a").state = NodeState.OK
        worker.run_once()
        first, second = live.wait_for(2)[:2]
        assert json.loads(first.payload)["state"] == "commissioning"
        assert json.loads(second.payload)["state"] == "ok", "the unchanged state was not published again"
    finally:
        worker.transport.close()
        live.close()
        clear_retained(*(f"{prefix}/{n}/state" for n in NODES), f"{prefix.replace('/nodes', '/gateway')}/status")


def test_an_unreachable_broker_fails_each_try_and_ends_dead(outbox_db, stop):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    settings = alerting({**mqtt_sink("x/nodes", max_attempts=2), "port": port})
    put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
    worker = sink_worker(settings, "scada", outbox_db, stop)
    worker.thread.start()
    wait_until(lambda: [d.status for d, _ in deliveries(outbox_db)] == [DeliveryStatus.DEAD], 20, 0.05,
               what="dead after 2 tries")
    (delivery, _), = deliveries(outbox_db)
    assert delivery.attempts == 2 and "cannot connect" in delivery.last_error


class SilentBroker:
    """Accepts an MQTT connection (CONNACK) and then never acknowledges a PUBLISH."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.connections: list[socket.socket] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self.listener.accept()
        except OSError:
            return
        self.connections.append(conn)
        conn.settimeout(10)
        try:
            conn.recv(1024)  # CONNECT
            conn.sendall(bytes([0x20, 0x02, 0x00, 0x00]))  # CONNACK, accepted
            while conn.recv(1024):  # swallow PUBLISH without PUBACK until the client goes
                pass
        except OSError:
            pass

    def close(self) -> None:
        self.listener.close()
        for conn in self.connections:
            conn.close()


def test_without_a_puback_the_try_fails_after_the_timeout(outbox_db):
    silent = SilentBroker()
    try:
        settings = alerting({**mqtt_sink("x/nodes"), "port": silent.port})
        sink = settings.sink("scada")
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
        with outbox_db.session() as session:
            item, = pending_heads(session, "scada")
        transport = MqttTransport(sink)  # without a database: events only
        with pytest.raises(DeliveryFailed, match=r"no PUBACK within 0\.5 s"):
            transport.send(item)
        transport.close()
    finally:
        silent.close()


def test_a_sensor_fault_is_retained_on_its_receiver_topic_until_its_clearing_replaces_it(broker, outbox_db, stop):
    prefix = unique_prefix()
    topic = f"{prefix}/node-a/receivers/5"
    live = Subscriber(f"{prefix}/+/receivers/#")
    try:
        settings = alerting(mqtt_sink(prefix))
        raised, cleared = sensor_fault_pair(settings, "node-a", dead_receiver(5))
        put_events(outbox_db, [raised])
        worker = sink_worker(settings, "scada", outbox_db, stop)
        worker.run_once()
        late = Subscriber(f"{prefix}/+/receivers/#")  # connects after the fact: the receiver's health at once
        try:
            retained, = late.wait_for(1)
        finally:
            late.close()
        assert retained.topic == topic and retained.retain and retained.qos == 1
        health = json.loads(retained.payload)
        assert health["faulty"] is True and health["kind"] == "sensor_fault" and health["event_id"] == str(raised.id)
        assert health["receiver"]["kind"] == "no_signal" and health["faulty_receivers"] == [5]
        assert health["node_id"] == "node-a" and health["links"]["measurement"].endswith("/measurements/7")

        put_events(outbox_db, [cleared])
        worker.run_once()
        messages = live.wait_for(2)
        assert [m.topic for m in messages] == [topic, topic]
        assert json.loads(messages[1].payload)["faulty"] is False
        late = Subscriber(f"{prefix}/+/receivers/#")
        try:
            retained, = late.wait_for(1)
        finally:
            late.close()
        assert json.loads(retained.payload) == json.loads(messages[1].payload)
        assert json.loads(retained.payload)["event_id"] == str(cleared.id)
    finally:
        live.close()
        clear_retained(topic, *(f"{prefix}/{n}/state" for n in NODES), f"{prefix.replace('/nodes', '/gateway')}/status")


@pytest.mark.e2e
def test_the_gateway_status_is_retained_and_its_last_will_says_offline_when_the_process_dies(broker, tmp_path):
    prefix = unique_prefix()
    gateway_topic = prefix.replace("/nodes", "/gateway")
    status = f"{gateway_topic}/status"
    db_path = tmp_path / "alerts.db"
    database = open_database(f"sqlite:///{db_path}")
    with database.write() as session:
        upsert_node(session, node_info("pipe-9"))
        session.get(NodeRow, "pipe-9").state = NodeState.OK
    database.dispose()
    config = tmp_path / "gateway.toml"
    config.write_text(
        f'[database]\nurl = "sqlite:///{db_path}"\n\n[[nodes]]\nid = "pipe-9"\nurl = "loop://"\n\n'
        f'[alerting]\npoll_interval_s = 0.1\n\n[[alerting.sinks]]\ntype = "mqtt"\nname = "scada"\n'
        f'host = "{BROKER[0]}"\nport = {BROKER[1]}\ntopic_prefix = "{prefix}"\ngateway_topic = "{gateway_topic}"\n'
        "state_interval_s = 0.2\ntimeout_s = 2\nkeepalive_s = 5\n")
    watcher = Subscriber(status)
    node_state = Subscriber(f"{prefix}/pipe-9/state")
    procs = []

    def deliver(name: str) -> Proc:
        proc = Proc([PYTHON, "-m", "alerts", "deliver", "--config", str(config), "--no-watch"], tmp_path, name)
        procs.append(proc)
        return proc

    def statuses() -> list[dict]:
        return [json.loads(m.payload) for m in watcher.messages if m.payload]

    try:
        first = deliver("deliver0")
        wait_until(lambda: any(s["online"] for s in statuses()), 30, what="the status online")
        node = json.loads(node_state.wait_for(1, timeout_s=30)[0].payload)
        assert node["state"] == "ok" and node["alarms"] == []
        first.kill()  # kill -9: no clean disconnect; the broker publishes the last will
        lost = wait_until(lambda: [s for s in statuses() if not s["online"]], 30, what="the last will")
        assert lost[-1]["reason"] == "connection lost" and lost[-1]["sink"] == "scada"
        assert retained_now(status, 1)[status]["online"] is False  # a subscriber connecting later sees it too

        second = deliver("deliver1")
        wait_until(lambda: statuses()[-1]["online"], 30, what="online again after the restart")
        assert second.terminate(timeout_s=10) == 0, second.stderr[-2000:]
        stopped = wait_until(lambda: not statuses()[-1]["online"] and statuses()[-1], 10, what="the clean stop")
        assert stopped["reason"] == "stopped"
    finally:
        watcher.close()
        node_state.close()
        for proc in procs:
            proc.close()
        clear_retained(status, f"{prefix}/pipe-9/state")
