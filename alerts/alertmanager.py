"""Prometheus Alertmanager sink: ``POST {url}/api/v2/alerts`` (postableAlerts).

Alertmanager identifies an alert by its label set and resolves it by itself when
``endsAt`` passes, so active alerts are re-sent every ``resend_interval_s`` with
``endsAt = now + 4 x resend_interval_s`` (what Prometheus does), and ended with
``endsAt`` = the time the pipe was found sound again. What is active is read from the
database — the newest state event per node this sink has acknowledged — so a restart
resumes the re-sends. The event id travels as the ``event_id`` annotation.

Alerts per node: ``PipeSentryPipeDamage`` (state suspected: severity warning; damage:
critical), ``PipeSentryMonitoringBlind`` (no_valid_baseline) and ``PipeSentryNodeOffline``;
per receiver of a node: ``PipeSentrySensorFault`` (sensor_fault fires it, its
sensor_fault_cleared ends it with the same labels). A node an admin decommissioned has its
alerts no longer re-sent: Alertmanager ends them when their ``endsAt`` passes. Other events (baseline changes, ...) are
not alerts here and are acknowledged without a request.
"""
from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from datetime import datetime, timedelta
from typing import Any

from alerts.config import AlertmanagerSinkSettings
from alerts.errors import AlertError
from alerts.events import (
    OUTAGE_KINDS,
    SENSOR_FAULT_KINDS,
    STATE_KINDS,
    EventKind,
    detection_text,
    fault_text,
    location_text,
)
from alerts.http_post import fingerprint, http_client, post
from alerts.outbox import OutboxEvent, delivered_events, latest_delivered
from db.clock import utc_now
from db.database import Database
from db.errors import StorageError
from db.nodes import decommissioned_node_ids

log = logging.getLogger("pipesentry.alerts")

ALERTS_PATH = "/api/v2/alerts"
RESEND_HORIZON = 4  # endsAt = now + this x resend interval
_STATE_ALERTS = {
    "suspected": ("PipeSentryPipeDamage", "warning"),
    "damage": ("PipeSentryPipeDamage", "critical"),
    "no_valid_baseline": ("PipeSentryMonitoringBlind", "warning"),
}
OFFLINE_ALERT = "PipeSentryNodeOffline"
SENSOR_FAULT_ALERT = "PipeSentrySensorFault"
# Every alert name this sink pushes (docker/alertmanager/alertmanager.yml routes and inhibits them).
ALERT_NAMES = tuple(dict.fromkeys([*(name for name, _ in _STATE_ALERTS.values()), OFFLINE_ALERT, SENSOR_FAULT_ALERT]))


def state_labels(node_id: str, state: str) -> dict[str, str]:
    alertname, severity = _STATE_ALERTS[state]
    return {"alertname": alertname, "node": node_id, "severity": severity, "state": state}


def offline_labels(node_id: str) -> dict[str, str]:
    return {"alertname": OFFLINE_ALERT, "node": node_id, "severity": "warning"}


def sensor_fault_labels(node_id: str, receiver: dict[str, Any]) -> dict[str, str]:
    """One alert per (node, receiver); ``kind`` is the fault as raised (its clearing carries the same)."""
    return {"alertname": SENSOR_FAULT_ALERT, "node": node_id, "rx_index": str(receiver["rx_index"]),
            "kind": str(receiver["kind"]), "severity": "warning"}


def rfc3339(moment: datetime) -> str:
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def postable_alerts(item: OutboxEvent, *, now: datetime, resend_interval_s: float, firing_only: bool = False) -> list[dict[str, Any]]:
    """The postableAlerts that tell Alertmanager what ``item`` means (empty: nothing to tell).

    A state event fires the alert of its new state and ends the node's other state alerts
    (so suspected -> damage ends the warning and fires the critical one), except that going
    blind keeps the alarm it came from firing; node_offline fires, node_online ends it;
    sensor_fault fires its receiver's alert, sensor_fault_cleared ends it.
    """
    payload = item.payload
    node_id = item.node_id
    if node_id is None:
        return []
    occurred_at = datetime.fromisoformat(payload["occurred_at"])
    firing_ends = now + timedelta(seconds=RESEND_HORIZON * resend_interval_s)
    annotations = _annotations(item)
    generator = (payload.get("links") or {}).get("measurement") or (payload.get("links") or {}).get("node")
    alerts: list[tuple[dict[str, str], bool]] = []
    if item.kind in STATE_KINDS:
        state = payload.get("state")
        alerts = [(state_labels(node_id, s), s == state) for s in _STATE_ALERTS]
        if item.kind == EventKind.MONITORING_BLIND:
            # Blind is not sound: a damage alert open before stays firing (and is re-sent).
            kept = payload.get("previous_state")
            alerts = [(labels, True) for labels, firing in alerts if firing or labels["state"] == kept]
    elif item.kind in OUTAGE_KINDS:
        alerts = [(offline_labels(node_id), item.kind == EventKind.NODE_OFFLINE)]
    elif item.kind in SENSOR_FAULT_KINDS:
        alerts = [(sensor_fault_labels(node_id, payload["receiver"]), item.kind == EventKind.SENSOR_FAULT)]
    result = []
    for labels, firing in alerts:
        if firing_only and not firing:
            continue
        alert: dict[str, Any] = {
            "labels": labels,
            "annotations": annotations,
            "startsAt": rfc3339(occurred_at),
            "endsAt": rfc3339(firing_ends if firing else occurred_at),
        }
        if generator:
            alert["generatorURL"] = generator
        result.append(alert)
    return result


def _annotations(item: OutboxEvent) -> dict[str, str]:
    payload = item.payload
    links = payload.get("links") or {}
    annotations = {
        "summary": str(payload.get("summary") or item.kind),
        "event_id": str(item.event_id),
        "event_kind": item.kind,
    }
    if item.kind in SENSOR_FAULT_KINDS:
        annotations["receiver"] = fault_text(payload.get("receiver"))
    else:
        annotations["location"] = location_text(payload.get("location"))
        annotations["di"] = detection_text(payload.get("detection"))
    for key in ("measurement", "di_map_png", "node"):
        if key in links:
            annotations[f"{key}_url"] = str(links[key])
    return annotations


def open_sensor_faults(delivered: list[OutboxEvent]) -> list[OutboxEvent]:
    """The sensor_fault events among ``delivered`` whose sensor_fault_cleared is not among them."""
    cleared = {str(i.payload.get("raised_event_id")) for i in delivered if i.kind == EventKind.SENSOR_FAULT_CLEARED}
    return [i for i in delivered if i.kind == EventKind.SENSOR_FAULT and str(i.event_id) not in cleared]


class AlertmanagerTransport:
    """Pushes state changes at once and re-sends what is active on every ``maintain()`` due."""

    def __init__(
        self,
        settings: AlertmanagerSinkSettings,
        database: Database,
        *,
        clock: Callable[[], datetime] = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.database = database
        self._clock = clock
        self._monotonic = monotonic
        self._client = http_client(settings.timeout_s)
        self._url = settings.url.rstrip("/") + ALERTS_PATH
        self._last_resend: float | None = None

    def endpoint_fingerprint(self) -> str:
        return fingerprint("alertmanager", self.settings.url)

    def send(self, item: OutboxEvent) -> None:
        alerts = postable_alerts(item, now=self._clock(), resend_interval_s=self.settings.resend_interval_s)
        if alerts:
            self._post(alerts)

    def maintain(self) -> None:
        """Re-send the active alerts when the resend interval has passed (failures wait for the next one)."""
        now_mono = self._monotonic()
        if self._last_resend is not None and now_mono - self._last_resend < self.settings.resend_interval_s:
            return
        self._last_resend = now_mono
        try:
            alerts = self.active_alerts()
            if alerts:
                self._post(alerts)
        except (AlertError, StorageError) as exc:
            log.warning("alertmanager %s: re-send of active alerts failed, next in %.0f s: %s",
                        self.settings.name, self.settings.resend_interval_s, exc)

    def active_alerts(self) -> list[dict[str, Any]]:
        """Firing alerts implied by the newest acknowledged state/outage event of each node and
        by each acknowledged sensor_fault whose clearing was not acknowledged yet."""
        now = self._clock()
        with self.database.session() as session:
            latest = latest_delivered(session, self.settings.name, STATE_KINDS) + latest_delivered(
                session, self.settings.name, OUTAGE_KINDS
            )
            latest += open_sensor_faults(delivered_events(session, self.settings.name, SENSOR_FAULT_KINDS))
            retired = decommissioned_node_ids(session)
        alerts = []
        for item in latest:
            if item.node_id in retired:
                continue  # decommissioned by an admin: not re-sent, so Alertmanager ends it at its endsAt
            alerts += postable_alerts(item, now=now, resend_interval_s=self.settings.resend_interval_s, firing_only=True)
        return alerts

    def _post(self, alerts: list[dict[str, Any]]) -> None:
        post(self._client, self._url, content=json.dumps(alerts).encode(), headers={},
             what=f"alertmanager {self.settings.name}")

    def close(self) -> None:
        self._client.close()
