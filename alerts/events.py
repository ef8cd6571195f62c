"""Pure builders of outbox events (``db.records.EventInput``): what happened, to which node, where.

Every event id is a UUIDv5 of the fact it reports (node, kind, measurement or outage), so
building the same event twice gives the same id: the outbox refuses a duplicate fact and
receivers can use the id as an idempotency key. Payloads are the typed models of
``alerts/payloads.py`` (a versioned contract) stored as their JSON, the same for all sinks;
each sink renders them (``alerts/webhook.py`` ... ``alerts/mqtt.py``).
"""
from __future__ import annotations

import logging
import uuid
from collections.abc import Mapping
from dataclasses import replace
from datetime import datetime
from enum import StrEnum
from typing import Any

from alerts.config import AlertingSettings
from alerts.payloads import (
    BaselineChangedPayload,
    Decommissioning,
    Detection,
    EndedBy,
    EventPayload,
    Links,
    Location,
    NodeDecommissionedPayload,
    NodeMisconfiguredPayload,
    NodeOfflinePayload,
    NodeOnlinePayload,
    NodeRecommissionedPayload,
    Receiver,
    SensorFaultClearedPayload,
    SensorFaultPayload,
    SinkDisabledPayload,
    StateChangePayload,
    StorageUnavailablePayload,
    payload_json,
)
from db.clock import utc_now
from db.models import NodeState, Severity
from db.records import EventInput

# Fixed namespace of PipeSentry event ids (uuid5); never change it, ids would stop matching.
EVENT_NAMESPACE = uuid.UUID("6f1c3f4e-2b7a-5d3e-9a41-7c2e1b0d5a90")


class EventKind(StrEnum):
    DAMAGE_RAISED = "damage_raised"  # to suspected or damage
    DAMAGE_CLEARED = "damage_cleared"  # from suspected/damage back to ok
    MONITORING_BLIND = "monitoring_blind"  # to no_valid_baseline: the pipe cannot be assessed
    MONITORING_RESTORED = "monitoring_restored"  # no_valid_baseline -> ok
    NODE_OFFLINE = "node_offline"
    NODE_ONLINE = "node_online"
    BASELINE_CHANGED = "baseline_changed"
    NODE_DECOMMISSIONED = "node_decommissioned"  # an admin took the node out of service (API)
    NODE_RECOMMISSIONED = "node_recommissioned"  # ... and put it back
    SINK_DISABLED = "sink_disabled"  # a receiver answered 410 Gone
    SENSOR_FAULT = "sensor_fault"  # a receiver (transducer channel) of a node became faulty
    SENSOR_FAULT_CLEARED = "sensor_fault_cleared"  # that receiver is healthy again
    NODE_MISCONFIGURED = "node_misconfigured"  # the port answers as another node, or it did not apply the settings
    STORAGE_UNAVAILABLE = "storage_unavailable"  # the gateway's writes failed for a while (disk full, I/O errors)


# The states whose entry raises damage, and how loudly.
ALARM_STATES = {NodeState.SUSPECTED: Severity.WARNING, NodeState.DAMAGE: Severity.CRITICAL}
# Kinds that carry a node's state transition (from_state -> to_state).
STATE_KINDS = frozenset(
    {EventKind.DAMAGE_RAISED, EventKind.DAMAGE_CLEARED, EventKind.MONITORING_BLIND, EventKind.MONITORING_RESTORED}
)
DAMAGE_KINDS = frozenset({EventKind.DAMAGE_RAISED, EventKind.DAMAGE_CLEARED})
OUTAGE_KINDS = frozenset({EventKind.NODE_OFFLINE, EventKind.NODE_ONLINE})
# Kinds about one receiver of a node (payload "receiver": {rx_index, rx_angle_deg, kind, ...}).
SENSOR_FAULT_KINDS = frozenset({EventKind.SENSOR_FAULT, EventKind.SENSOR_FAULT_CLEARED})


# How loud an event is in the daemon's log: as loud as it is to operators. A baseline change or a node
# back online is routine (INFO); an outage or a blind node is a warning; damage is an error-level line.
_LOG_LEVELS = {Severity.INFO: logging.INFO, Severity.WARNING: logging.WARNING, Severity.CRITICAL: logging.ERROR}


def log_level(severity: Severity | str) -> int:
    """The logging level an event of this severity is logged at."""
    return _LOG_LEVELS[Severity(severity)]


def event_id(*parts: object) -> uuid.UUID:
    """The stable id of the fact named by ``parts``."""
    return uuid.uuid5(EVENT_NAMESPACE, "/".join(str(p) for p in parts))


def measurement_url(api_base_url: str, measurement_id: int) -> str:
    return f"{api_base_url}/api/v1/measurements/{measurement_id}"


def di_map_png_url(api_base_url: str, measurement_id: int) -> str:
    return f"{api_base_url}/api/v1/measurements/{measurement_id}/di-maps/gateway.png"


def node_url(api_base_url: str, node_id: str) -> str:
    return f"{api_base_url}/api/v1/nodes/{node_id}"


def measurement_links(api_base_url: str, measurement_id: int) -> dict[str, str]:
    """The API links of a measurement: its record and its gateway DI map (PNG)."""
    return {"measurement": measurement_url(api_base_url, measurement_id),
            "di_map_png": di_map_png_url(api_base_url, measurement_id)}


def state_change_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    from_state: NodeState | str,
    to_state: NodeState | str,
    measurement_id: int | None,
    peak_di: float | None,
    threshold: float | None,
    axial_mm: float | None = None,
    angle_deg: float | None = None,
    occurred_at: datetime | None = None,
    reason: str | None = None,
    region: Mapping[str, Any] | None = None,
) -> EventInput | None:
    """The alert of a plain state transition, or None when it is not one operators need.

    to suspected/damage: ``damage_raised`` (warning/critical); suspected/damage -> ok:
    ``damage_cleared``; -> no_valid_baseline: ``monitoring_blind`` (an open damage alert stays
    open: a blind node has not shown the pipe is sound); no_valid_baseline -> ok:
    ``monitoring_restored``. Commissioning/calibrating transitions give None. ``reason``: why the
    imaging abstained (the detection's ``abstain_reason``), carried by ``monitoring_blind``.
    The gateway decides with the node's open alarms instead (``alerts.alarms.alarm_events``),
    which also ends them by re-baseline and after blind spells; this is the transition alone.
    """
    before, after = NodeState(from_state), NodeState(to_state)
    if before == after:
        return None
    if after in ALARM_STATES:
        kind = EventKind.DAMAGE_RAISED
    elif after == NodeState.OK and before in ALARM_STATES:
        kind = EventKind.DAMAGE_CLEARED
    elif after == NodeState.NO_VALID_BASELINE:
        kind = EventKind.MONITORING_BLIND
    elif after == NodeState.OK and before == NodeState.NO_VALID_BASELINE:
        kind = EventKind.MONITORING_RESTORED
    else:
        return None
    return alarm_state_event(
        settings, kind, node_id=node_id, from_state=before, to_state=after, measurement_id=measurement_id,
        peak_di=peak_di, threshold=threshold, axial_mm=axial_mm, angle_deg=angle_deg, occurred_at=occurred_at,
        reason=reason, region=region,
    )


def alarm_state_event(
    settings: AlertingSettings,
    kind: EventKind,
    *,
    node_id: str,
    from_state: NodeState | str,
    to_state: NodeState | str,
    measurement_id: int | None,
    peak_di: float | None,
    threshold: float | None,
    axial_mm: float | None = None,
    angle_deg: float | None = None,
    occurred_at: datetime | None = None,
    reason: str | None = None,
    alarm_id: uuid.UUID | None = None,
    ended_by: EndedBy | None = None,
    routing: Severity | None = None,
    sinks: tuple[str, ...] | None = None,
    region: Mapping[str, Any] | None = None,
) -> EventInput:
    """One of the node's damage/blind alarm events (``STATE_KINDS``), raise or end.

    A raise is one id per (kind, node, measurement, transition); an end, given the ``alarm_id``
    (the id of the raise that opened it), one id per alarm: an alarm ends once. ``alarm_id`` on a
    raise: the alarm it escalates. ``ended_by``: why it ended (default: recovery); ``routing``: an
    end's routing severity (the alarm's; default from ``from_state``); ``sinks``: who must hear it
    (default: the routing's).
    """
    before, after = NodeState(from_state), NodeState(to_state)
    if kind == EventKind.DAMAGE_RAISED:
        severity = ALARM_STATES[after]
        routing = severity
    elif kind == EventKind.MONITORING_BLIND:
        severity = routing = Severity.WARNING
    elif kind == EventKind.DAMAGE_CLEARED:
        severity = Severity.INFO
        routing = routing or ALARM_STATES.get(before, Severity.WARNING)
    elif kind == EventKind.MONITORING_RESTORED:
        severity, routing = Severity.INFO, routing or Severity.WARNING
    else:
        raise ValueError(f"{kind} is not a state alarm kind")
    occurred_at = occurred_at or utc_now()
    ends = kind in (EventKind.DAMAGE_CLEARED, EventKind.MONITORING_RESTORED)
    if ends and alarm_id is not None:
        eid = event_id(kind, alarm_id)
    else:
        fact = measurement_id if measurement_id is not None else occurred_at.isoformat()
        eid = event_id(kind, node_id, fact, f"{before}->{after}")
    if ends:
        ended_by = ended_by or EndedBy(cause="recovery")
    detection = _detection(peak_di, threshold)
    location = _location(axial_mm, angle_deg, region)
    payload = StateChangePayload(
        **_common(settings, eid, kind, node_id, severity, routing, occurred_at, measurement_id),
        summary=_state_summary(kind, node_id, before, after, detection, location, reason, ended_by),
        state=after, previous_state=before, online=True, detection=detection, location=location,
        reason=reason if kind == EventKind.MONITORING_BLIND and reason else None,
        alarm="damage" if kind in DAMAGE_KINDS else "blind", alarm_id=alarm_id or eid,
        ended_by=ended_by if ends else None,
    )
    return _event(settings, payload, routing, sinks)


def node_offline_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    state: NodeState | str,
    last_seen_at: datetime,
    now: datetime | None = None,
    after: uuid.UUID | None = None,
    never_seen: bool = False,
) -> EventInput:
    """``node_offline`` (warning): the node has not answered since ``last_seen_at``; ``never_seen``:
    it has never answered, and ``last_seen_at`` is when the gateway started watching it.

    One outage (one ``last_seen_at``) gives one event id, however often it is checked. ``after``:
    the end of an earlier offline alarm with the same ``last_seen_at`` (ended by a decommissioning:
    the node was recommissioned and is still silent), which makes this a new alarm.
    """
    now = now or utc_now()
    fact = (node_id, last_seen_at.isoformat()) if after is None else (node_id, last_seen_at.isoformat(), after)
    eid = event_id(EventKind.NODE_OFFLINE, *fact)
    offline_s = max(0.0, (now - last_seen_at).total_seconds())
    since = f"{last_seen_at:%Y-%m-%d %H:%M:%S} UTC"
    summary = (f"node {node_id} offline: never answered, watched for {_duration(offline_s)} (since {since})"
               if never_seen else f"node {node_id} offline: not seen for {_duration(offline_s)} (since {since})")
    payload = NodeOfflinePayload(
        **_common(settings, eid, EventKind.NODE_OFFLINE, node_id, Severity.WARNING, Severity.WARNING, now),
        summary=summary, state=NodeState(state), previous_state=NodeState(state), online=False,
        last_seen_at=last_seen_at, offline_for_s=round(offline_s, 1), alarm="offline", alarm_id=eid,
        never_seen=True if never_seen else None,
    )
    return _event(settings, payload, Severity.WARNING)


def node_online_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    state: NodeState | str,
    offline_event_id: uuid.UUID,
    offline_since: datetime,
    seen_at: datetime,
    ended_by: EndedBy | None = None,
    sinks: tuple[str, ...] | None = None,
    first_seen: bool = False,
) -> EventInput:
    """``node_online`` (info, routed like the offline alert it ends): the node answers again (``first_seen``:
    for the first time, its node_offline said never_seen) — or, ``ended_by`` a decommissioning, its offline
    alarm ends with it out of service (still not online)."""
    eid = event_id(EventKind.NODE_ONLINE, offline_event_id)
    down_s = max(0.0, (seen_at - offline_since).total_seconds())
    ended_by = ended_by or EndedBy(cause="recovery")
    recovered = ended_by.cause == "recovery"
    first_seen = first_seen and recovered
    if first_seen:
        summary = f"node {node_id} answered for the first time, after {_duration(down_s)} watched, state {state}"
    elif recovered:
        summary = f"node {node_id} back online after {_duration(down_s)}, state {state}"
    else:
        summary = f"node {node_id} offline alarm ended after {_duration(down_s)}{end_text(ended_by)}"
    payload = NodeOnlinePayload(
        **_common(settings, eid, EventKind.NODE_ONLINE, node_id, Severity.INFO, Severity.WARNING, seen_at),
        summary=summary, state=NodeState(state), previous_state=NodeState(state), online=recovered,
        offline_event_id=offline_event_id, offline_since=offline_since, offline_for_s=round(down_s, 1),
        alarm="offline", alarm_id=offline_event_id, ended_by=ended_by, first_seen=True if first_seen else None,
    )
    return _event(settings, payload, Severity.WARNING, sinks)


def baseline_changed_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    baseline_id: int,
    measurement_id: int,
    previous_measurement_id: int | None,
    created_by: str,
    reason: str,
    state: NodeState | str,
    occurred_at: datetime | None = None,
) -> EventInput:
    """``baseline_changed`` (info): the node's DI maps are now computed against another measurement."""
    occurred_at = occurred_at or utc_now()
    eid = event_id(EventKind.BASELINE_CHANGED, node_id, baseline_id)
    previous = "none" if previous_measurement_id is None else f"measurement {previous_measurement_id}"
    payload = BaselineChangedPayload(
        **_common(settings, eid, EventKind.BASELINE_CHANGED, node_id, Severity.INFO, Severity.INFO, occurred_at,
                  measurement_id),
        summary=f"node {node_id} baseline changed to measurement {measurement_id} (was {previous}) by {created_by}: {reason}",
        state=NodeState(state), previous_state=NodeState(state), online=True,
        baseline_id=baseline_id, previous_measurement_id=previous_measurement_id, created_by=created_by, reason=reason,
    )
    return _event(settings, payload, Severity.INFO)


def node_decommissioned_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    state: NodeState | str,
    decommissioned_at: datetime,
    by: str,
    reason: str,
) -> EventInput:
    """``node_decommissioned`` (info): the gateway no longer polls the node and raises no outage
    alert for it. One decommissioning (one ``decommissioned_at``) gives one event id."""
    eid = event_id(EventKind.NODE_DECOMMISSIONED, node_id, decommissioned_at.isoformat())
    payload = NodeDecommissionedPayload(
        **_common(settings, eid, EventKind.NODE_DECOMMISSIONED, node_id, Severity.INFO, Severity.INFO,
                  decommissioned_at),
        summary=f"node {node_id} decommissioned by {by}: {reason} (not polled, no outage alerts)",
        state=NodeState(state), previous_state=NodeState(state), online=False,
        decommissioned=Decommissioning(at=decommissioned_at, by=by, reason=reason),
    )
    return _event(settings, payload, Severity.INFO)


def node_recommissioned_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    state: NodeState | str,
    decommissioned_at: datetime,
    occurred_at: datetime | None = None,
) -> EventInput:
    """``node_recommissioned`` (info): the node decommissioned at ``decommissioned_at`` is polled again."""
    occurred_at = occurred_at or utc_now()
    eid = event_id(EventKind.NODE_RECOMMISSIONED, node_id, decommissioned_at.isoformat())
    payload = NodeRecommissionedPayload(
        **_common(settings, eid, EventKind.NODE_RECOMMISSIONED, node_id, Severity.INFO, Severity.INFO, occurred_at),
        summary=f"node {node_id} back in service (decommissioned since {decommissioned_at:%Y-%m-%d %H:%M} UTC)",
        state=NodeState(state), previous_state=NodeState(state), online=False,
        decommissioned=None, decommissioned_since=decommissioned_at,
    )
    return _event(settings, payload, Severity.INFO)


def node_misconfigured_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    state: NodeState | str,
    problems: list[str],
    boot_id: int,
    occurred_at: datetime | None = None,
) -> EventInput:
    """``node_misconfigured`` (warning): the node on the port is not the configured one (its INFO
    names another node: nothing is stored until that is fixed), or it does not run the settings
    configured (records are stored with the settings it states). One id per node, boot and set
    of problems, so a problem that persists is told once per boot of the node."""
    occurred_at = occurred_at or utc_now()
    eid = event_id(EventKind.NODE_MISCONFIGURED, node_id, boot_id, *sorted(problems))
    payload = NodeMisconfiguredPayload(
        **_common(settings, eid, EventKind.NODE_MISCONFIGURED, node_id, Severity.WARNING, Severity.WARNING,
                  occurred_at),
        summary=f"node {node_id} misconfigured: " + "; ".join(problems),
        state=NodeState(state), previous_state=NodeState(state), online=True,
        problems=list(problems), boot_id=boot_id,
    )
    return _event(settings, payload, Severity.WARNING)


def sink_disabled_event(
    settings: AlertingSettings,
    *,
    sink_name: str,
    endpoint_fingerprint: str,
    status_code: int,
    occurred_at: datetime | None = None,
) -> EventInput:
    """``sink_disabled`` (warning): a receiver said 410 Gone; told to every other sink."""
    occurred_at = occurred_at or utc_now()
    eid = event_id(EventKind.SINK_DISABLED, sink_name, endpoint_fingerprint)
    payload = SinkDisabledPayload(
        **_common(settings, eid, EventKind.SINK_DISABLED, None, Severity.WARNING, Severity.WARNING, occurred_at),
        summary=f"alert sink {sink_name} disabled: its receiver answered HTTP {status_code} (Gone); "
        "change its URL in the gateway config to enable it again",
        state=None, previous_state=None, online=None,
        sink=sink_name, endpoint_fingerprint=endpoint_fingerprint, status_code=status_code,
    )
    event = _event(settings, payload, Severity.WARNING)
    return replace(event, sinks=tuple(n for n in event.sinks if n != sink_name))


def storage_unavailable_event(
    settings: AlertingSettings,
    *,
    since: datetime,
    until: datetime,
    failed_writes: int,
    reason: str,
) -> EventInput:
    """``storage_unavailable`` (warning): the gateway's writes failed from ``since`` until ``until``; one id
    per outage. Written by the first writes that fit again (during the outage nothing can be)."""
    eid = event_id(EventKind.STORAGE_UNAVAILABLE, since.isoformat())
    lasted_s = max(0.0, (until - since).total_seconds())
    payload = StorageUnavailablePayload(
        **_common(settings, eid, EventKind.STORAGE_UNAVAILABLE, None, Severity.WARNING, Severity.WARNING, until),
        summary=f"storage unavailable for {lasted_s:.0f} s from {since.isoformat(timespec='seconds')}: "
        f"{failed_writes} write(s) failed ({reason}); measurements acquired meanwhile were not stored",
        state=None, previous_state=None, online=None,
        since=since, until=until, failed_writes=failed_writes, reason=reason,
    )
    return _event(settings, payload, Severity.WARNING)


def sensor_fault_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    fault: dict[str, Any],
    measurement_id: int,
    state: NodeState | str,
    faulty_receivers: list[int],
    consecutive: int,
    occurred_at: datetime | None = None,
) -> EventInput:
    """``sensor_fault`` (warning): a receiver was faulty in ``consecutive`` measurements in a row.

    ``fault`` is the receiver's entry of ``detections.sensor_faults`` in this measurement
    (``imaging.health.SensorFault.as_dict()``: rx_index, rx_angle_deg, kind, amplitude_ratio,
    delay_s). The receiver is left out of the DI map until it is healthy again, so the
    node sees less of the pipe. One id per (node, receiver, measurement that raised it).
    """
    occurred_at = occurred_at or utc_now()
    receiver = _receiver(fault)
    eid = event_id(EventKind.SENSOR_FAULT, node_id, receiver.rx_index, measurement_id)
    payload = SensorFaultPayload(
        **_common(settings, eid, EventKind.SENSOR_FAULT, node_id, Severity.WARNING, Severity.WARNING, occurred_at,
                  measurement_id),
        summary=f"node {node_id} {_receiver_text(receiver)} faulty: {fault_text(receiver.model_dump())} in "
        f"{consecutive} consecutive measurements; left out of the DI map, coverage reduced",
        state=NodeState(state), previous_state=NodeState(state), online=True,
        receiver=receiver, faulty_receivers=sorted(faulty_receivers), consecutive_measurements=consecutive,
        alarm="sensor_fault", alarm_id=eid,
    )
    return _event(settings, payload, Severity.WARNING)


def sensor_fault_cleared_event(
    settings: AlertingSettings,
    *,
    node_id: str,
    raised_event_id: uuid.UUID,
    raised_receiver: dict[str, Any],
    raised_measurement_id: int | None,
    measurement_id: int | None,
    state: NodeState | str,
    faulty_receivers: list[int],
    consecutive: int,
    occurred_at: datetime | None = None,
    ended_by: EndedBy | None = None,
    sinks: tuple[str, ...] | None = None,
) -> EventInput:
    """``sensor_fault_cleared`` (info, routed like the ``sensor_fault`` it ends): the receiver
    was healthy in ``consecutive`` measurements in a row and is back in the DI map — or, ``ended_by``
    a decommissioning (no measurement), its alarm ends with the node out of service.

    ``raised_receiver`` is the ``receiver`` of the ``sensor_fault`` event it clears (the same
    rx_index and kind, so Alertmanager resolves the same label set). One clearing per raise:
    the id is derived from the raised event's id.
    """
    occurred_at = occurred_at or utc_now()
    receiver = _receiver(raised_receiver)
    eid = event_id(EventKind.SENSOR_FAULT_CLEARED, raised_event_id)
    since = "" if raised_measurement_id is None else f" since measurement {raised_measurement_id}"
    ended_by = ended_by or EndedBy(cause="recovery")
    if ended_by.cause == "recovery":
        summary = (f"node {node_id} {_receiver_text(receiver)} healthy again in {consecutive} consecutive "
                   f"measurements (was {receiver.kind}{since}); back in the DI map")
    else:
        summary = f"node {node_id} {_receiver_text(receiver)} alarm ended (was {receiver.kind}{since}){end_text(ended_by)}"
    payload = SensorFaultClearedPayload(
        **_common(settings, eid, EventKind.SENSOR_FAULT_CLEARED, node_id, Severity.INFO, Severity.WARNING,
                  occurred_at, measurement_id),
        summary=summary, state=NodeState(state), previous_state=NodeState(state), online=True,
        receiver=receiver, faulty_receivers=sorted(faulty_receivers), consecutive_measurements=consecutive,
        raised_event_id=raised_event_id, raised_measurement_id=raised_measurement_id,
        alarm="sensor_fault", alarm_id=raised_event_id, ended_by=ended_by,
    )
    return _event(settings, payload, Severity.WARNING, sinks)


def _common(
    settings: AlertingSettings,
    eid: uuid.UUID,
    kind: EventKind,
    node_id: str | None,
    severity: Severity,
    routing: Severity,
    occurred_at: datetime,
    measurement_id: int | None = None,
) -> dict[str, Any]:
    """The fields every payload has that the builders do not each decide."""
    base = settings.api_base_url
    links = Links(
        node=None if node_id is None else node_url(base, node_id),
        measurement=None if measurement_id is None else measurement_url(base, measurement_id),
        di_map_png=None if measurement_id is None else di_map_png_url(base, measurement_id),
    )
    return dict(event_id=eid, kind=kind, node_id=node_id, severity=severity, routing_severity=routing,
                occurred_at=occurred_at, measurement_id=measurement_id, links=links)


def _event(
    settings: AlertingSettings, payload: EventPayload, routing: Severity, sinks: tuple[str, ...] | None = None
) -> EventInput:
    """The outbox event of ``payload``, for the sinks that want ``routing`` (or ``sinks``)."""
    return EventInput(kind=EventKind(payload.kind), severity=payload.severity, payload=payload_json(payload),
                      sinks=settings.sink_names_for(routing) if sinks is None else sinks, id=payload.event_id)


def detection_of(peak_di: float | None, threshold: float | None) -> Detection | None:
    """The payload's ``detection``: the DI peak against the threshold (None without a peak)."""
    return _detection(peak_di, threshold)


def location_of(axial_mm: float | None, angle_deg: float | None,
                region: Mapping[str, Any] | None = None) -> Location | None:
    """The payload's ``location`` (None when the estimate is unknown); ``region``: the estimate's 90 %
    localization region as the imaging gives it (``Defect.as_dict()["region"]``), when known."""
    return _location(axial_mm, angle_deg, region)


def _detection(peak_di: float | None, threshold: float | None) -> Detection | None:
    if peak_di is None:
        return None
    ratio = peak_di / threshold if threshold else None
    return Detection(peak_di=float(peak_di), threshold=None if threshold is None else float(threshold),
                     di_over_threshold=None if ratio is None else round(float(ratio), 4))


def _location(axial_mm: float | None, angle_deg: float | None,
              region: Mapping[str, Any] | None = None) -> Location | None:
    if axial_mm is None or angle_deg is None:
        return None
    if not region:
        return Location(axial_mm=round(float(axial_mm), 1), angle_deg=round(float(angle_deg), 1))
    return Location(axial_mm=round(float(axial_mm), 1), angle_deg=round(float(angle_deg), 1),
                    axial_half_mm=round(float(region["axial_half_mm"]), 1),
                    circumferential_half_mm=round(float(region["circumferential_half_mm"]), 1),
                    localized=bool(region.get("localized", True)))


def location_text(location: dict[str, Any] | None) -> str:
    if not location:
        return "location unknown"
    return f"{location['axial_mm']:.0f} mm axial, {location['angle_deg']:.0f} deg"


def detection_text(detection: dict[str, Any] | None) -> str:
    if not detection:
        return "DI n/a"
    if detection.get("threshold") is None:
        return f"DI {detection['peak_di']:.3g} (no threshold yet)"
    return f"DI {detection['peak_di']:.3g} vs threshold {detection['threshold']:.3g}"


def _receiver(fault: dict[str, Any]) -> Receiver:
    """A sensor fault as it travels in events: rx_index, rx_angle_deg, kind, amplitude_ratio, delay_s."""
    try:
        rx_index, kind = int(fault["rx_index"]), str(fault["kind"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"a sensor fault needs an integer rx_index and a kind, got {fault!r}") from exc
    return Receiver(
        rx_index=rx_index,
        rx_angle_deg=_number(fault.get("rx_angle_deg")),
        kind=kind,
        amplitude_ratio=_number(fault.get("amplitude_ratio")),
        delay_s=_number(fault.get("delay_s")),
    )


def _number(value: Any) -> float | None:
    return None if value is None else float(value)


def _receiver_text(receiver: Receiver) -> str:
    angle = receiver.rx_angle_deg
    return f"receiver {receiver.rx_index}" + ("" if angle is None else f" ({angle:.0f} deg)")


def fault_text(receiver: dict[str, Any] | None) -> str:
    """What is wrong with a receiver, in words (imaging/health.py's kinds)."""
    if not receiver:
        return "fault n/a"
    kind, ratio, delay = receiver.get("kind"), receiver.get("amplitude_ratio"), receiver.get("delay_s")
    if kind == "no_signal":
        return "no signal" + ("" if ratio is None else f" (direct arrival at {ratio:.0%} of baseline)")
    if kind == "amplitude" and ratio is not None:
        return f"amplitude (direct arrival at {ratio:.0%} of baseline)"
    if kind == "timing" and delay is not None:
        return f"timing (direct arrival shifted {delay * 1e6:+.2f} us)"
    return str(kind)


def _state_summary(
    kind: EventKind,
    node_id: str,
    from_state: NodeState,
    to_state: NodeState,
    detection: Detection | None,
    location: Location | None,
    reason: str | None = None,
    ended_by: EndedBy | None = None,
) -> str:
    di = detection_text(None if detection is None else detection.model_dump())
    if kind == EventKind.DAMAGE_RAISED:
        where = location_text(None if location is None else location.model_dump())
        return f"{to_state.upper()} on node {node_id}: {di} at {where}"
    if kind == EventKind.MONITORING_BLIND:
        why = reason or "no valid baseline for current conditions"
        return f"node {node_id} cannot assess the pipe: {why} (was {from_state})"
    cause = end_text(ended_by)
    if ended_by is not None and ended_by.cause == "decommissioning":
        alarm = "damage" if kind == EventKind.DAMAGE_CLEARED else "blind-monitoring"
        return f"{alarm} alarm on node {node_id} ended{cause}"
    reading = f", {di}" if detection is not None else ""
    if kind == EventKind.DAMAGE_CLEARED:
        return f"cleared on node {node_id}: {from_state} → {to_state}{reading}{cause}"
    return f"node {node_id} monitoring again: {from_state} → {to_state}{reading}{cause}"


def end_text(ended_by: EndedBy | None) -> str:
    """Why an alarm ended, for summaries: nothing for a recovery."""
    if ended_by is None or ended_by.cause == "recovery":
        return ""
    what = {"rebaseline": "new baseline", "decommissioning": "node decommissioned"}[ended_by.cause]
    who = f" by {ended_by.by}" if ended_by.by else ""
    why = f": {ended_by.reason}" if ended_by.reason else ""
    return f" ({what}{who}{why})"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
