"""The real Mosquitto broker on 127.0.0.1:1883 as a test peer: a fixture, a recording subscriber, cleanup.

Tests use unique topic prefixes (the broker is shared with other test runs) and remove the
retained messages they leave. Without a broker the tests skip with the reason; under CI they fail.
"""
from __future__ import annotations

import socket
import threading
import uuid

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.support.peers import peer_missing

BROKER = ("127.0.0.1", 1883)


@pytest.fixture(scope="module")
def broker() -> tuple[str, int]:
    try:
        socket.create_connection(BROKER, timeout=2).close()
    except OSError as exc:
        peer_missing(f"no MQTT broker on {BROKER[0]}:{BROKER[1]} ({exc}); "
                     "start it: mosquitto -d -c /etc/mosquitto/mosquitto.conf")
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


def clear_retained(*topics: str) -> None:
    """Remove retained messages the test left on the shared broker."""
    client = mqtt.Client(CallbackAPIVersion.VERSION2)
    client.connect(*BROKER)
    client.loop_start()
    for topic in topics:
        client.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
    client.disconnect()
    client.loop_stop()


