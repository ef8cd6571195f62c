"""Prometheus Alertmanager sink: ``POST {url}/api/v2/alerts`` (postableAlerts).

Alertmanager identifies an alert by its label set and resolves it by itself when ``endsAt``
passes, so active alerts are re-sent every ``resend_interval_s`` with ``endsAt = now + 4 x
resend_interval_s`` (what Prometheus does), and ended with ``endsAt`` = the time the alarm
ended (alerts/alarms.py: by recovery, re-baseline or decommissioning). What is active is read
from the database — per node and alarm, the newest event this sink has acknowledged — so a
restart resumes the re-sends; a re-send carries the node's *current* DI, estimate and map, not
the values of when it was raised. The event id travels as the ``event_id`` annotation.

Alerts per node: ``PipeSentryPipeDamage`` (the damage alarm: state suspected, severity
warning; damage: critical), ``PipeSentryMonitoringBlind`` (the blind alarm) and
``PipeSentryNodeOffline``; per receiver of a node: ``PipeSentrySensorFault``. Each alarm event
fires or ends its own alert: damage_raised fires the alert of its state and ends the other
severity's, damage_cleared ends both, monitoring_blind / monitoring_restored, node_offline /
node_online, sensor_fault / sensor_fault_cleared likewise. ``labels`` in the sink's settings
are added to every alert (e.g. the site, for a central Alertmanager's routes and inhibitions).
Other events (baseline changes, ...) are not alerts here and are acknowledged without a request.
"""
from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from alerts.config import AlertmanagerSinkSettings
from alerts.errors import AlertError
from alerts.events import (
    DAMAGE_KINDS,
    OUTAGE_KINDS,
    SENSOR_FAULT_KINDS,
    STATE_KINDS,
    EventKind,
    detection_of,
    detection_text,
    fault_text,
    location_of,
    location_text,
    measurement_links,
)
from alerts.http_post import fingerprint, http_client, post
from alerts.outbox import OutboxEvent, delivered_events, latest_delivered
from alerts.payloads import PayloadPart
from db.clock import utc_now
from db.database import Database
from db.errors import StorageError
from db.models import NodeState
from db.nodes import list_nodes
from db.queries import latest_detections

log = logging.getLogger("pipesentry.alerts")

ALERTS_PATH = "/api/v2/alerts"
RESEND_HORIZON = 4  # endsAt = now + this x resend interval
DAMAGE_ALERT = "PipeSentryPipeDamage"
BLIND_ALERT = "PipeSentryMonitoringBlind"
OFFLINE_ALERT = "PipeSentryNodeOffline"
SENSOR_FAULT_ALERT = "PipeSentrySensorFault"
_DAMAGE_SEVERITY = {"suspected": "warning", "damage": "critical"}
# Every alert name this sink pushes (docker/alertmanager/alertmanager.yml routes and inhibits them).
ALERT_NAMES = (DAMAGE_ALERT, BLIND_ALERT, OFFLINE_ALERT, SENSOR_FAULT_ALERT)
BLIND_KINDS = frozenset({EventKind.MONITORING_BLIND, EventKind.MONITORING_RESTORED})
# The node states in which a stored damage / blind alarm may still be active (a guard for
# events older than schema 2, whose ends did not cover every way out of an alarm).
_DAMAGE_ACTIVE_STATES = {NodeState.SUSPECTED, NodeState.DAMAGE, NodeState.NO_VALID_BASELINE}


def damage_labels(node_id: str, state: str) -> dict[str, str]:
    return {"alertname": DAMAGE_ALERT, "node": node_id, "severity": _DAMAGE_SEVERITY[state], "state": state}


def blind_labels(node_id: str) -> dict[str, str]:
    return {"alertname": BLIND_ALERT, "node": node_id, "severity": "warning", "state": NodeState.NO_VALID_BASELINE.value}


def offline_labels(node_id: str) -> dict[str, str]:
    return {"alertname": OFFLINE_ALERT, "node": node_id, "severity": "warning"}


def sensor_fault_labels(node_id: str, receiver: dict[str, Any]) -> dict[str, str]:
    """One alert per (node, receiver); ``kind`` is the fault as raised (its clearing carries the same)."""
    return {"alertname": SENSOR_FAULT_ALERT, "node": node_id, "rx_index": str(receiver["rx_index"]),
            "kind": str(receiver["kind"]), "severity": "warning"}


def rfc3339(moment: datetime) -> str:
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass(frozen=True)
class CurrentReading:
    """A node's latest verdict, which a re-sent damage or blind alert shows instead of the raise's."""

    measurement_id: int
    peak_di: float | None
    threshold: float | None
    axial_mm: float | None
    angle_deg: float | None
    abstain_reason: str | None


def alert_changes(item: OutboxEvent) -> list[tuple[dict[str, str], bool]]:
    """The label sets ``item`` fires (True) or ends (False); empty when it is not an alert here."""
    node_id, payload = item.node_id, item.payload
    if node_id is None:
        return []
    if item.kind == EventKind.DAMAGE_RAISED:
        state = payload["state"]
        return [(damage_labels(node_id, s), s == state) for s in _DAMAGE_SEVERITY]
    if item.kind == EventKind.DAMAGE_CLEARED:
        return [(damage_labels(node_id, s), False) for s in _DAMAGE_SEVERITY]
    if item.kind in BLIND_KINDS:
        return [(blind_labels(node_id), item.kind == EventKind.MONITORING_BLIND)]
    if item.kind in OUTAGE_KINDS:
        return [(offline_labels(node_id), item.kind == EventKind.NODE_OFFLINE)]
    if item.kind in SENSOR_FAULT_KINDS:
        return [(sensor_fault_labels(node_id, payload["receiver"]), item.kind == EventKind.SENSOR_FAULT)]
    return []


def postable_alerts(
    item: OutboxEvent,
    *,
    now: datetime,
    resend_interval_s: float,
    firing_only: bool = False,
    current: CurrentReading | None = None,
    api_base_url: str | None = None,
    extra_labels: Mapping[str, str] | None = None,
) -> list[dict[str, Any]]:
    """The postableAlerts that tell Alertmanager what ``item`` means (empty: nothing to tell).

    ``current``: the node's latest verdict, shown by a re-sent damage or blind alert (its DI,
    estimate and map links; ``api_base_url`` makes the links); ``firing_only``: leave the ends out.
    """
    payload = item.payload
    occurred_at = datetime.fromisoformat(payload["occurred_at"])
    firing_ends = now + timedelta(seconds=RESEND_HORIZON * resend_interval_s)
    annotations = _annotations(item, current, api_base_url)
    generator = annotations.get("measurement_url") or annotations.get("node_url")
    result = []
    for labels, firing in alert_changes(item):
        if firing_only and not firing:
            continue
        alert: dict[str, Any] = {
            "labels": {**(extra_labels or {}), **labels},
            "annotations": annotations,
            "startsAt": rfc3339(occurred_at),
            "endsAt": rfc3339(firing_ends if firing else occurred_at),
        }
        if generator:
            alert["generatorURL"] = generator
        result.append(alert)
    return result


def _annotations(item: OutboxEvent, current: CurrentReading | None, api_base_url: str | None) -> dict[str, str]:
    payload = item.payload
    links = dict(payload.get("links") or {})
    annotations = {"summary": str(payload.get("summary") or item.kind), "event_id": str(item.event_id),
                   "event_kind": item.kind}
    if payload.get("alarm_id"):
        annotations["alarm_id"] = str(payload["alarm_id"])
    if payload.get("ended_by"):
        annotations["ended_by"] = str(payload["ended_by"].get("cause"))
    if item.kind in SENSOR_FAULT_KINDS:
        annotations["receiver"] = fault_text(payload.get("receiver"))
    elif item.kind in STATE_KINDS:
        detection, location, reason = payload.get("detection"), payload.get("location"), payload.get("reason")
        if current is not None:  # a re-send: what the node reads now
            detection = _dumped(detection_of(current.peak_di, current.threshold))
            location = _dumped(location_of(current.axial_mm, current.angle_deg))
            reason = current.abstain_reason
            if api_base_url is not None:
                links.update(measurement_links(api_base_url, current.measurement_id))
            if item.kind == EventKind.DAMAGE_RAISED:
                raised = datetime.fromisoformat(payload["occurred_at"])
                annotations["summary"] = (f"{str(payload['state']).upper()} on node {item.node_id}: "
                                          f"{detection_text(detection)} at {location_text(location)} "
                                          f"(raised {raised:%Y-%m-%d %H:%M} UTC)")
        annotations["di"] = detection_text(detection)
        annotations["location"] = location_text(location)
        if item.kind == EventKind.MONITORING_BLIND and reason:
            annotations["reason"] = str(reason)
    for key in ("measurement", "di_map_png", "node"):
        if key in links:
            annotations[f"{key}_url"] = str(links[key])
    return annotations


def _dumped(part: PayloadPart | None) -> dict[str, Any] | None:
    return None if part is None else part.model_dump()


def open_sensor_faults(delivered: list[OutboxEvent]) -> list[OutboxEvent]:
    """The sensor_fault events among ``delivered`` whose sensor_fault_cleared is not among them."""
    cleared = {str(i.payload.get("raised_event_id")) for i in delivered if i.kind == EventKind.SENSOR_FAULT_CLEARED}
    return [i for i in delivered if i.kind == EventKind.SENSOR_FAULT and str(i.event_id) not in cleared]


class AlertmanagerTransport:
    """Pushes alarm events at once and re-sends what is active on every ``maintain()`` due."""

    def __init__(
        self,
        settings: AlertmanagerSinkSettings,
        database: Database,
        *,
        api_base_url: str | None = None,
        clock: Callable[[], datetime] = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.database = database
        self.api_base_url = api_base_url
        self._clock = clock
        self._monotonic = monotonic
        self._client = http_client(settings.timeout_s)
        self._url = settings.url.rstrip("/") + ALERTS_PATH
        self._last_resend: float | None = None

    def endpoint_fingerprint(self) -> str:
        return fingerprint("alertmanager", self.settings.url)

    def send(self, item: OutboxEvent) -> None:
        alerts = postable_alerts(item, now=self._clock(), resend_interval_s=self.settings.resend_interval_s,
                                 extra_labels=self.settings.labels)
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
        """The firing alerts of the alarms this sink was told of and not told the end of: per node, the
        newest acknowledged damage, blind and outage event, and each acknowledged sensor_fault whose
        clearing it has not acknowledged — for the nodes in service, with their current reading."""
        now = self._clock()
        name = self.settings.name
        with self.database.session() as session:
            nodes = {n.node_id: n.state for n in list_nodes(session, include_decommissioned=False)}
            damage = latest_delivered(session, name, DAMAGE_KINDS)
            blind = latest_delivered(session, name, BLIND_KINDS)
            outages = latest_delivered(session, name, OUTAGE_KINDS)
            faults = open_sensor_faults(delivered_events(session, name, SENSOR_FAULT_KINDS))
            readings = {node: CurrentReading(d.measurement_id, d.peak_di, d.threshold, d.axial_mm, d.angle_deg,
                                             d.abstain_reason)
                        for node, d in latest_detections(session, list(nodes)).items()}
        active = [i for i in damage if nodes.get(str(i.node_id)) in _DAMAGE_ACTIVE_STATES]
        active += [i for i in blind if nodes.get(str(i.node_id)) == NodeState.NO_VALID_BASELINE]
        active += [i for i in outages + faults if i.node_id in nodes]  # decommissioned: left out, so they end
        alerts = []
        for item in active:
            current = readings.get(str(item.node_id)) if item.kind in STATE_KINDS else None
            alerts += postable_alerts(item, now=now, resend_interval_s=self.settings.resend_interval_s,
                                      firing_only=True, current=current, api_base_url=self.api_base_url,
                                      extra_labels=self.settings.labels)
        return alerts

    def _post(self, alerts: list[dict[str, Any]]) -> None:
        post(self._client, self._url, content=json.dumps(alerts).encode(), headers={},
             what=f"alertmanager {self.settings.name}")

    def close(self) -> None:
        self._client.close()
