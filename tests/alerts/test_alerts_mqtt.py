"""MQTT sink against the real Mosquitto broker on 127.0.0.1:1883: retained QoS 1 state per node, PUBACK awaited."""
from __future__ import annotations

import json
import os
import socket
import threading
import uuid

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from alerts.errors import DeliveryFailed
from alerts.mqtt import MqttTransport
from alerts.outbox import pending_heads
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
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(60)
BROKER = ("127.0.0.1", 1883)


@pytest.fixture(scope="module")
def broker() -> tuple[str, int]:
    try:
        socket.create_connection(BROKER, timeout=2).close()
    except OSError as exc:
        reason = f"no MQTT broker on {BROKER[0]}:{BROKER[1]} ({exc}); start it: mosquitto -d -c /etc/mosquitto/mosquitto.conf"
        if os.environ.get("CI") == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    return BROKER


class Subscriber:
    """A real MQTT client recording what arrives on a topic filter."""

    def __init__(self, topic: str) -> None:
        self.messages: list[mqtt.MQTTMessage] = []
        self._cond = threading.Condition()
        self._subscribed = threading.Event()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"test-sub-{uuid.uuid4().hex[:8]}")
        self.client.on_connect = lambda c, *_: c.subscribe(topic, qos=1)
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect(*BROKER)
        self.client.loop_start()
        assert self._subscribed.wait(10), "subscription not acknowledged"

    def _on_message(self, client, userdata, message) -> None:
        with self._cond:
            self.messages.append(message)
            self._cond.notify_all()

    def wait_for(self, count: int, timeout_s: float = 10) -> list[mqtt.MQTTMessage]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.messages) >= count, timeout_s), \
                f"got {len(self.messages)} of {count} messages"
            return list(self.messages)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def clear_retained(prefix: str, node_ids) -> None:
    client = mqtt.Client(CallbackAPIVersion.VERSION2)
    client.connect(*BROKER)
    client.loop_start()
    for node_id in node_ids:
        client.publish(f"{prefix}/{node_id}/state", b"", qos=1, retain=True).wait_for_publish(5)
    client.disconnect()
    client.loop_stop()


def mqtt_sink(prefix: str, **policy) -> dict:
    return {"type": "mqtt", "name": "scada", "host": BROKER[0], "port": BROKER[1], "topic_prefix": prefix,
            **fast_policy(**policy)}


def test_each_node_state_is_published_retained_with_qos_1_in_order(broker, outbox_db, stop):
    prefix = f"pstest-{uuid.uuid4().hex[:8]}/nodes"
    live = Subscriber(f"{prefix}/+/state")
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
            got = [json.loads(m.payload)["event_id"] for m in received if m.topic == f"{prefix}/{node_id}/state"]
            assert got == sent
        assert all(m.qos == 1 for m in received)

        late = Subscriber(f"{prefix}/+/state")  # connects after the fact: gets the retained state at once
        try:
            retained = late.wait_for(2)
            assert all(m.retain for m in retained)
            last = {json.loads(m.payload)["node_id"]: json.loads(m.payload) for m in retained}
            assert last["node-a"]["state"] == "suspected" and last["node-a"]["kind"] == "damage_raised"
            assert last["node-a"]["event_id"] == str(events[-2].id)
            assert last["node-a"]["links"]["di_map_png"].endswith("/di-maps/gateway.png")
            assert last["node-a"]["location"] == {"axial_mm": 200.0, "angle_deg": 90.0}
        finally:
            late.close()
    finally:
        live.close()
        clear_retained(prefix, ("node-a", "node-b"))


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
        transport = MqttTransport(sink)
        with pytest.raises(DeliveryFailed, match=r"no PUBACK within 0\.5 s"):
            transport.send(item)
        transport.close()
    finally:
        silent.close()


def test_a_sensor_fault_is_retained_on_its_receiver_topic_until_its_clearing_replaces_it(broker, outbox_db, stop):
    prefix = f"pstest-{uuid.uuid4().hex[:8]}/nodes"
    topic = f"{prefix}/node-a/receivers/5"
    live = Subscriber(f"{prefix}/#")
    try:
        settings = alerting(mqtt_sink(prefix))
        raised, cleared = sensor_fault_pair(settings, "node-a", dead_receiver(5))
        put_events(outbox_db, [raised])
        worker = sink_worker(settings, "scada", outbox_db, stop)
        worker.run_once()
        late = Subscriber(f"{prefix}/#")  # connects after the fact: the receiver's health at once
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
        assert [m.topic for m in messages] == [topic, topic], "the node's state topic is left alone"
        assert json.loads(messages[1].payload)["faulty"] is False
        late = Subscriber(f"{prefix}/#")
        try:
            retained, = late.wait_for(1)
        finally:
            late.close()
        assert json.loads(retained.payload) == json.loads(messages[1].payload)
        assert json.loads(retained.payload)["event_id"] == str(cleared.id)
    finally:
        live.close()
        clear_topic(topic)


def clear_topic(topic: str) -> None:
    client = mqtt.Client(CallbackAPIVersion.VERSION2)
    client.connect(*BROKER)
    client.loop_start()
    client.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
    client.disconnect()
    client.loop_stop()
