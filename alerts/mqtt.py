"""MQTT sink: each node's latest state as a retained QoS 1 message on ``{topic_prefix}/{node_id}/state``.

A subscriber that connects at any time gets the node's current state at once (retained);
every event about the node replaces it, in order. Sensor fault events go instead to the
receiver's own retained topic ``{topic_prefix}/{node_id}/receivers/{rx_index}``
(``"faulty": true`` from sensor_fault, replaced by ``"faulty": false`` from
sensor_fault_cleared), so the state topic keeps the node's state. An attempt counts as delivered only
when the broker's PUBACK arrived within ``timeout_s``. The payload's ``event_id`` is the
idempotency key. Events without a node go, not retained, to ``gateway_topic``.
"""
from __future__ import annotations

import json
import threading
import uuid
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from alerts.config import MqttSinkSettings
from alerts.errors import DeliveryFailed
from alerts.events import SENSOR_FAULT_KINDS, EventKind
from alerts.http_post import fingerprint
from alerts.outbox import OutboxEvent

QOS = 1
GATEWAY_TOPIC = "pipesentry/gateway/events"


def state_topic(settings: MqttSinkSettings, node_id: str) -> str:
    return f"{settings.topic_prefix.rstrip('/')}/{node_id}/state"


def receiver_topic(settings: MqttSinkSettings, node_id: str, rx_index: int) -> str:
    return f"{settings.topic_prefix.rstrip('/')}/{node_id}/receivers/{rx_index}"


def mqtt_topic(settings: MqttSinkSettings, item: OutboxEvent) -> tuple[str, bool]:
    """Where ``item`` is published and whether retained."""
    if item.node_id is None:
        return GATEWAY_TOPIC, False
    if item.kind in SENSOR_FAULT_KINDS:
        return receiver_topic(settings, item.node_id, int(item.payload["receiver"]["rx_index"])), True
    return state_topic(settings, item.node_id), True


def mqtt_message(item: OutboxEvent) -> dict[str, Any]:
    """The JSON document published for ``item`` (the node's state after the event; for a
    sensor fault event, the receiver's health: ``faulty``, ``receiver``, ``faulty_receivers``)."""
    payload = item.payload
    keys = ("node_id", "state", "previous_state", "online", "severity", "occurred_at", "summary",
            "measurement_id", "detection", "location", "links")
    message = {"event_id": str(item.event_id), "kind": item.kind, **{k: payload.get(k) for k in keys}}
    if item.kind == EventKind.NODE_DECOMMISSIONED:  # the retained state says so until it is recommissioned
        message["decommissioned"] = payload.get("decommissioned")
    if item.kind in SENSOR_FAULT_KINDS:
        message.update(faulty=item.kind == EventKind.SENSOR_FAULT, receiver=payload.get("receiver"),
                       faulty_receivers=payload.get("faulty_receivers"))
    return message


class MqttTransport:
    """One paho-mqtt client (CallbackAPIVersion.VERSION2), connected on demand, torn down on any failure."""

    def __init__(self, settings: MqttSinkSettings) -> None:
        self.settings = settings
        self._client: mqtt.Client | None = None
        self._connected = threading.Event()
        self._connect_error: str | None = None

    def endpoint_fingerprint(self) -> str:
        return fingerprint("mqtt", self.settings.host, str(self.settings.port), self.settings.topic_prefix)

    def send(self, item: OutboxEvent) -> None:
        client = self._connection()
        topic, retain = mqtt_topic(self.settings, item)
        body = json.dumps(mqtt_message(item), separators=(",", ":"), sort_keys=True)
        info = client.publish(topic, body, qos=QOS, retain=retain)
        try:
            info.wait_for_publish(timeout=self.settings.timeout_s)
        except (RuntimeError, ValueError) as exc:
            self._teardown()
            raise DeliveryFailed(f"mqtt {self.settings.name}: publish failed: {exc}") from exc
        if not info.is_published():
            self._teardown()  # a late PUBACK would be for a message we will send again anyway
            raise DeliveryFailed(f"mqtt {self.settings.name}: no PUBACK within {self.settings.timeout_s:g} s")

    def _connection(self) -> mqtt.Client:
        if self._client is not None and self._client.is_connected():
            return self._client
        self._teardown()
        s = self.settings
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=f"pipesentry-{s.name}-{uuid.uuid4().hex[:12]}",
            clean_session=True,
        )
        client.connect_timeout = s.timeout_s
        if s.username is not None:
            client.username_pw_set(s.username, None if s.password is None else s.password.get_secret_value())
        if s.tls:
            client.tls_set()
        self._connected.clear()
        self._connect_error = None
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        self._client = client
        try:
            client.connect(s.host, s.port, keepalive=s.keepalive_s)
        except OSError as exc:
            self._teardown()
            raise DeliveryFailed(f"mqtt {s.name}: cannot connect to {s.host}:{s.port}: {exc}") from exc
        client.loop_start()
        if not self._connected.wait(s.timeout_s) or self._connect_error is not None:
            why = self._connect_error or f"no CONNACK within {s.timeout_s:g} s"
            self._teardown()
            raise DeliveryFailed(f"mqtt {s.name}: {why}")
        return client

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            self._connect_error = f"broker refused the connection: {reason_code}"
        self._connected.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        self._connected.clear()

    def _teardown(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        client.disconnect()  # queues DISCONNECT; the network loop then ends by itself
        client.loop_stop()  # joins paho's network thread

    def maintain(self) -> None:
        """Nothing to refresh: retained messages stay on the broker."""

    def close(self) -> None:
        self._teardown()
