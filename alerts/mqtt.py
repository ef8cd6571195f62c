"""MQTT sink: each node's current state retained, its events as a stream, the gateway's own status with a last will.

Topics (``topic_prefix`` default ``pipesentry/nodes``, ``gateway_topic`` default ``pipesentry/gateway``):

* ``{topic_prefix}/{node_id}/state`` — retained, QoS 1: one **current-state document** per node
  (``node_state_document``), read from the database and published again whenever it changes
  (a state change, a new verdict, an alarm raised or ended, the node going offline or
  decommissioned) — every change of state, including those that raise no event (commissioning,
  calibrating, calibrating -> ok). A subscriber that connects at any time gets each node's state
  at once. It is not an event: the events are on the next topic.
* ``{topic_prefix}/{node_id}/events`` — not retained, QoS 1: every event about the node, in
  order (the outbox delivery: delivered once the broker's PUBACK arrived within ``timeout_s``;
  the payload's ``event_id`` is the idempotency key).
* ``{topic_prefix}/{node_id}/receivers/{rx_index}`` — retained: a receiver's health from its
  sensor fault events (``"faulty": true`` from sensor_fault, replaced by ``"faulty": false`` from
  sensor_fault_cleared).
* ``{gateway_topic}/status`` — retained: ``{"online": true, ...}`` while this process is
  connected; the broker publishes the last will ``{"online": false, "reason": "connection lost"}``
  when it goes without a word (power cut, kill -9, network), and a clean stop says
  ``"reason": "stopped"``. ``{gateway_topic}/events``: events about no node (sink_disabled, storage_unavailable).

The state documents are kept current by ``maintain()`` (at most every ``state_interval_s``);
after a (re)connection every node's document is published again, so a broker that lost its
retained messages is repaired.
"""
from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from collections.abc import Callable
from datetime import datetime
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from alerts.alarms import NodeAlarms, OpenAlarm, open_alarms_by_node
from alerts.config import AlertingSettings, MqttSinkSettings
from alerts.errors import DeliveryFailed
from alerts.events import (
    SENSOR_FAULT_KINDS,
    EventKind,
    detection_of,
    location_of,
    measurement_links,
    node_url,
)
from alerts.http_post import fingerprint
from alerts.outbox import OutboxEvent
from alerts.payloads import PAYLOAD_SCHEMA, PayloadPart
from db.clock import utc_now
from db.database import Database
from db.errors import StorageError
from db.models import DetectionRow, NodeRow
from db.nodes import list_nodes
from db.queries import latest_detections
from db.release import release_labels
from retry_timing.backoff import Backoff

log = logging.getLogger("pipesentry.alerts")

QOS = 1
RECONNECT_CAP_S = 60.0  # a failed state refresh is retried after at most this (full-jitter backoff)
# Fields of a state document that change without the state changing (left out of "has it changed").
_VOLATILE = ("updated_at", "last_seen_at")


def state_topic(settings: MqttSinkSettings, node_id: str) -> str:
    return f"{settings.topic_prefix.rstrip('/')}/{node_id}/state"


def events_topic(settings: MqttSinkSettings, node_id: str) -> str:
    return f"{settings.topic_prefix.rstrip('/')}/{node_id}/events"


def receiver_topic(settings: MqttSinkSettings, node_id: str, rx_index: int) -> str:
    return f"{settings.topic_prefix.rstrip('/')}/{node_id}/receivers/{rx_index}"


def status_topic(settings: MqttSinkSettings) -> str:
    return f"{settings.gateway_topic.rstrip('/')}/status"


def gateway_events_topic(settings: MqttSinkSettings) -> str:
    return f"{settings.gateway_topic.rstrip('/')}/events"


def mqtt_publications(settings: MqttSinkSettings, item: OutboxEvent) -> list[tuple[str, dict[str, Any], bool]]:
    """Where ``item`` is published: (topic, document, retained) — the node's event stream, and a sensor
    fault event also its receiver's retained health; an event without a node the gateway's events."""
    message = mqtt_message(item)
    if item.node_id is None:
        return [(gateway_events_topic(settings), message, False)]
    published = [(events_topic(settings, item.node_id), message, False)]
    if item.kind in SENSOR_FAULT_KINDS:
        rx_index = int(item.payload["receiver"]["rx_index"])
        published.append((receiver_topic(settings, item.node_id, rx_index), message, True))
    return published


def mqtt_message(item: OutboxEvent) -> dict[str, Any]:
    """The JSON document of an event (its payload's essentials; a sensor fault event's also says
    the receiver's health: ``faulty``, ``receiver``, ``faulty_receivers``)."""
    payload = item.payload
    keys = ("schema", "node_id", "state", "previous_state", "online", "severity", "occurred_at", "summary",
            "measurement_id", "detection", "location", "links", "alarm", "alarm_id", "ended_by", "decommissioned")
    message = {"event_id": str(item.event_id), "kind": item.kind, **{k: payload.get(k) for k in keys if k in payload}}
    if item.kind in SENSOR_FAULT_KINDS:
        message.update(faulty=item.kind == EventKind.SENSOR_FAULT, receiver=payload.get("receiver"),
                       faulty_receivers=payload.get("faulty_receivers"))
    return message


def node_state_document(
    node: NodeRow, detection: DetectionRow | None, alarms: NodeAlarms, *, api_base_url: str, now: datetime
) -> dict[str, Any]:
    """A node's current state as the retained ``state`` topic carries it (pure)."""
    links = {"node": node_url(api_base_url, node.node_id)}
    reading = None
    if detection is not None:
        links.update(measurement_links(api_base_url, detection.measurement_id))
        reading = {
            "measurement_id": detection.measurement_id,
            "measured_at": detection.created_at.isoformat(),
            "detection": _json(detection_of(detection.peak_di, detection.threshold)),
            "location": _json(location_of(detection.axial_mm, detection.angle_deg)),
            "abstain_reason": detection.abstain_reason,
        }
    decommissioned = None
    if node.decommissioned_at is not None:
        decommissioned = {"at": node.decommissioned_at.isoformat(), "by": node.decommissioned_by,
                          "reason": node.decommission_reason}
    return {
        "schema": PAYLOAD_SCHEMA,
        "node_id": node.node_id,
        "state": node.state.value,
        "online": bool(node.online) and decommissioned is None,
        "decommissioned": decommissioned,
        # As node_offline carries it: never seen, since when the gateway watches it (and never_seen true).
        "last_seen_at": (node.watched_since if node.last_seen_at is None else node.last_seen_at).isoformat(),
        **({"never_seen": True} if node.never_seen else {}),
        "latest": reading,
        "alarms": [_alarm_summary(a) for a in alarms.all()],
        "faulty_receivers": sorted(a.rx_index for a in alarms.sensor_faults if a.rx_index is not None),
        "links": links,
        "updated_at": now.isoformat(),
    }


def _json(part: PayloadPart | None) -> dict[str, Any] | None:
    return None if part is None else part.model_dump(mode="json")


def _alarm_summary(alarm: OpenAlarm) -> dict[str, Any]:
    summary = {"alarm": str(alarm.alarm), "alarm_id": str(alarm.alarm_id), "severity": str(alarm.routing),
               "since": alarm.raised_at.isoformat(), "summary": alarm.payload.get("summary")}
    if alarm.rx_index is not None:
        summary["rx_index"] = alarm.rx_index
    return summary


def _stable(document: dict[str, Any]) -> str:
    return json.dumps({k: v for k, v in document.items() if k not in _VOLATILE}, sort_keys=True, default=str)


class MqttTransport:
    """One paho-mqtt client (CallbackAPIVersion.VERSION2) with a last will, torn down on any failure."""

    def __init__(
        self,
        settings: MqttSinkSettings,
        alerting: AlertingSettings | None = None,
        database: Database | None = None,
        *,
        clock: Callable[[], datetime] = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.api_base_url = (alerting or AlertingSettings()).api_base_url
        self.database = database
        self._clock = clock
        self._monotonic = monotonic
        self._client: mqtt.Client | None = None
        self._connected = threading.Event()
        self._connect_error: str | None = None
        self._published: dict[str, str] = {}  # node -> the state document last acknowledged (stable part)
        self._next_sync = 0.0
        self._failures = 0
        # Many gateways may share one broker: after its outage they come back spread out.
        self._backoff = Backoff(settings.backoff_base_s, max(RECONNECT_CAP_S, settings.backoff_base_s), "full")

    def endpoint_fingerprint(self) -> str:
        return fingerprint("mqtt", self.settings.host, str(self.settings.port), self.settings.topic_prefix)

    def send(self, item: OutboxEvent) -> None:
        client = self._connection()
        for topic, message, retain in mqtt_publications(self.settings, item):
            self._publish(client, topic, message, retain=retain)

    def maintain(self) -> None:
        """Keep each node's retained state document current (at most every ``state_interval_s``, and at
        once after a reconnection); a failure is logged and retried with backoff, never raised."""
        if self.database is None or self._monotonic() < self._next_sync:
            return
        try:
            client = self._connection()
            published = self.sync_states(client)
        except (DeliveryFailed, StorageError) as exc:
            self._failures += 1
            wait_s = self._backoff.delay_s(self._failures)
            self._next_sync = self._monotonic() + wait_s
            log.warning("mqtt %s: node states not published, next try in %.0f s: %s", self.settings.name, wait_s, exc)
            return
        self._failures = 0
        self._next_sync = self._monotonic() + self.settings.state_interval_s
        if published:
            log.debug("mqtt %s: %d node state(s) published", self.settings.name, published)

    def sync_states(self, client: mqtt.Client) -> int:
        """Publish the state document of every node whose document changed since it was last acknowledged."""
        assert self.database is not None
        now = self._clock()
        with self.database.session() as session:
            nodes = list(list_nodes(session))
            detections = latest_detections(session, [n.node_id for n in nodes])
            alarms = open_alarms_by_node(session, with_sinks=False)
        count = 0
        for node in nodes:
            document = node_state_document(node, detections.get(node.node_id), alarms.get(node.node_id, NodeAlarms()),
                                           api_base_url=self.api_base_url, now=now)
            stable = _stable(document)
            if self._published.get(node.node_id) == stable:
                continue
            self._publish(client, state_topic(self.settings, node.node_id), document, retain=True)
            self._published[node.node_id] = stable
            count += 1
        return count

    def _publish(self, client: mqtt.Client, topic: str, document: dict[str, Any], *, retain: bool) -> None:
        body = json.dumps(document, separators=(",", ":"), sort_keys=True)
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
        # The broker tells every subscriber if this process vanishes without a word.
        client.will_set(status_topic(s), self._status(False, "connection lost"), qos=QOS, retain=True)
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
        self._published.clear()  # a new session: every node's state again (the broker may have lost them)
        self._next_sync = 0.0
        self._publish(client, status_topic(s), json.loads(self._status(True)), retain=True)
        return client

    def _status(self, online: bool, reason: str | None = None) -> str:
        status: dict[str, Any] = {"online": online, "at": self._clock().isoformat(), "sink": self.settings.name,
                                  "version": release_labels()["version"]}
        if reason is not None:
            status["reason"] = reason
        return json.dumps(status, separators=(",", ":"), sort_keys=True)

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

    def close(self) -> None:
        """A clean stop: the status says so (a clean DISCONNECT does not fire the will), then disconnect."""
        client = self._client
        if client is not None and client.is_connected():
            try:
                self._publish(client, status_topic(self.settings), json.loads(self._status(False, "stopped")),
                              retain=True)
            except DeliveryFailed as exc:
                log.warning("mqtt %s: could not say the gateway stopped: %s", self.settings.name, exc)
        self._teardown()
