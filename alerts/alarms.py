"""Alarms: what was raised about a node and has not ended, which sinks were told, and the rule that ends them.

An *alarm* is a problem told to the sinks that must, some day, be told to have ended:

| alarm | raised by | ended by |
|---|---|---|
| damage | ``damage_raised`` (suspected, then damage: one alarm, escalated) | ``damage_cleared`` |
| blind | ``monitoring_blind`` | ``monitoring_restored`` |
| offline | ``node_offline`` | ``node_online`` |
| sensor fault (per receiver) | ``sensor_fault`` | ``sensor_fault_cleared`` |

An alarm ends by *recovery* (the pipe reads sound again, the node answers, the receiver is
healthy), by *re-baseline* (an operator set a new active baseline: the node calibrates again
and its old alarms no longer mean anything) or by *decommissioning* (an admin took the node
out of service). Each end is the alarm's own ending event with ``ended_by`` saying which,
so every sink closes it the way it closes a recovery.

Which sinks must hear the end: every sink with a delivery of one of the alarm's raises,
whatever became of it (delivered, pending, dead: a receiver may have seen a raise whose
acknowledgement was lost, and the end of an alarm a receiver never saw is harmless, while an
alarm left open is not), plus the sinks the end's own routing reaches; sinks no longer in the
config are left out. A sink whose ``min_severity`` kept it from the raise gets no end either.

Nothing is kept in memory: the open alarms are read from the outbox (``open_alarms``), in the
transaction that adds the ends, so a restart neither forgets an alarm nor ends one twice (an
end's id derives from the alarm's). The rules themselves (``alarm_change``) are pure.
"""
from __future__ import annotations

import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from datetime import datetime
from enum import StrEnum
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from alerts.config import AlertingSettings
from alerts.events import (
    ALARM_STATES,
    EventKind,
    alarm_state_event,
    node_online_event,
    sensor_fault_cleared_event,
)
from alerts.payloads import EndedBy
from db.models import DeliveryRow, EventRow, NodeState, Severity
from db.records import EventInput


class Alarm(StrEnum):
    DAMAGE = "damage"
    BLIND = "blind"
    OFFLINE = "offline"
    SENSOR_FAULT = "sensor_fault"


class EndCause(StrEnum):
    RECOVERY = "recovery"  # the node itself says the problem is gone
    REBASELINE = "rebaseline"  # an operator set a new active baseline (with its reason)
    DECOMMISSIONING = "decommissioning"  # an admin took the node out of service (with the reason)


RAISED_BY = {
    EventKind.DAMAGE_RAISED: Alarm.DAMAGE,
    EventKind.MONITORING_BLIND: Alarm.BLIND,
    EventKind.NODE_OFFLINE: Alarm.OFFLINE,
    EventKind.SENSOR_FAULT: Alarm.SENSOR_FAULT,
}
ENDED_BY = {
    EventKind.DAMAGE_CLEARED: Alarm.DAMAGE,
    EventKind.MONITORING_RESTORED: Alarm.BLIND,
    EventKind.NODE_ONLINE: Alarm.OFFLINE,
    EventKind.SENSOR_FAULT_CLEARED: Alarm.SENSOR_FAULT,
}
ALARM_KINDS = frozenset(RAISED_BY) | frozenset(ENDED_BY)


@dataclass(frozen=True)
class OpenAlarm:
    """A raised alarm of a node that no end has followed yet."""

    alarm: Alarm
    alarm_id: uuid.UUID  # the id of the event that first raised it (the alarm's identity)
    latest_event_id: uuid.UUID  # its newest raise (an escalation suspected -> damage is another raise)
    raised_at: datetime  # when it was first raised
    routing: Severity  # the routing severity of its newest raise (its end is routed the same)
    payload: dict[str, Any]  # the newest raise's payload (state, detection, receiver, ...)
    sinks: frozenset[str] = frozenset()  # sinks with a delivery of any of its raises

    @property
    def state(self) -> str | None:
        """For a damage alarm: the state it was raised for (suspected or damage)."""
        return self.payload.get("state")

    @property
    def rx_index(self) -> int | None:
        receiver = self.payload.get("receiver")
        return None if receiver is None else int(receiver["rx_index"])


@dataclass(frozen=True)
class NodeAlarms:
    """A node's open alarms (read before a decision, from the outbox)."""

    damage: OpenAlarm | None = None
    blind: OpenAlarm | None = None
    offline: OpenAlarm | None = None
    sensor_faults: tuple[OpenAlarm, ...] = ()

    def all(self) -> list[OpenAlarm]:
        return [a for a in (self.damage, self.blind, self.offline) if a is not None] + list(self.sensor_faults)


@dataclass(frozen=True)
class AlarmEnd:
    """One open alarm a decision ends, and why."""

    alarm: OpenAlarm
    cause: EndCause
    by: str | None = None  # who (the operator who set the baseline, the admin who decommissioned)
    reason: str | None = None  # their reason
    baseline_id: int | None = None  # re-baseline: the baseline record that ended it

    def ended_by(self) -> EndedBy:
        """The end's ``ended_by`` in event payloads."""
        if self.cause == EndCause.RECOVERY:
            return EndedBy(cause="recovery")
        cause: Literal["rebaseline", "decommissioning"] = (
            "rebaseline" if self.cause == EndCause.REBASELINE else "decommissioning")
        return EndedBy(cause=cause, by=self.by, reason=self.reason, baseline_id=self.baseline_id)


@dataclass(frozen=True)
class BaselineSet:
    """The node's active baseline record, as an end by re-baseline names it."""

    baseline_id: int
    set_at: datetime
    by: str
    reason: str


@dataclass(frozen=True)
class AlarmChange:
    """What one monitor verdict does to the node's damage and blind alarms (``alarm_change``)."""

    ends: tuple[AlarmEnd, ...] = ()
    raise_damage: bool = False  # raise (or escalate, de-escalate) the damage alarm for the new state
    raise_blind: bool = False

    def __bool__(self) -> bool:
        return bool(self.ends or self.raise_damage or self.raise_blind)


def alarm_change(alarms: NodeAlarms, *, state: str, baseline: BaselineSet | None) -> AlarmChange:
    """The damage and blind alarms a node in ``state`` should have, against those open (pure).

    The damage alarm is wanted in ``suspected`` and ``damage`` (at that state's severity), and
    kept in ``no_valid_baseline`` if it was open (blind is not sound); the blind alarm in
    ``no_valid_baseline``. A wanted alarm that is not open (or open at another severity) is
    raised; an open one that is no longer wanted ends — by re-baseline when the node's active
    baseline was set after the alarm was raised (the node went ``calibrating``, or reads sound
    against the new baseline), else by recovery.
    """
    want_damage = state in ALARM_STATES or (state == NodeState.NO_VALID_BASELINE and alarms.damage is not None)
    want_blind = state == NodeState.NO_VALID_BASELINE
    ends = []
    for open_alarm, wanted in ((alarms.damage, want_damage), (alarms.blind, want_blind)):
        if open_alarm is not None and not wanted:
            ends.append(_end_after(open_alarm, baseline))
    raise_damage = state in ALARM_STATES and (alarms.damage is None or alarms.damage.state != state)
    raise_blind = want_blind and alarms.blind is None
    return AlarmChange(ends=tuple(ends), raise_damage=raise_damage, raise_blind=raise_blind)


def _end_after(alarm: OpenAlarm, baseline: BaselineSet | None) -> AlarmEnd:
    if baseline is not None and baseline.set_at > alarm.raised_at:
        return AlarmEnd(alarm, EndCause.REBASELINE, by=baseline.by, reason=baseline.reason,
                        baseline_id=baseline.baseline_id)
    return AlarmEnd(alarm, EndCause.RECOVERY)


def decommissioning_ends(alarms: NodeAlarms, *, by: str, reason: str) -> list[AlarmEnd]:
    """Every open alarm of a node an admin decommissioned ends, with who and why (pure)."""
    return [AlarmEnd(alarm, EndCause.DECOMMISSIONING, by=by, reason=reason) for alarm in alarms.all()]


def end_sinks(settings: AlertingSettings, alarm: OpenAlarm, routing: Severity) -> tuple[str, ...]:
    """The configured sinks that must hear ``alarm`` end: those that had any of its raises, and those
    the end's ``routing`` reaches (in config order)."""
    reached = set(settings.sink_names_for(routing)) | alarm.sinks
    return tuple(s.name for s in settings.sinks if s.name in reached)


# ------------------------------------------------------------------ reading what is open (I/O)
def open_alarms(session: Session, node_id: str) -> NodeAlarms:
    """The node's open alarms, from its alarm events in the outbox (oldest first) and their deliveries."""
    rows = session.scalars(
        select(EventRow)
        .where(EventRow.node_id == node_id, EventRow.kind.in_([str(k) for k in ALARM_KINDS]))
        .order_by(EventRow.created_at, EventRow.id)
    ).all()
    return _fold(rows, _sinks_of(session, [r.id for r in rows if r.kind in RAISED_BY]))


def open_alarms_by_node(session: Session, *, with_sinks: bool = True) -> dict[str, NodeAlarms]:
    """Every node's open alarms (nodes without any are absent); ``with_sinks=False`` leaves out who had them."""
    rows = session.scalars(
        select(EventRow)
        .where(EventRow.node_id.is_not(None), EventRow.kind.in_([str(k) for k in ALARM_KINDS]))
        .order_by(EventRow.created_at, EventRow.id)
    ).all()
    sinks = _sinks_of(session, [r.id for r in rows if r.kind in RAISED_BY]) if with_sinks else {}
    by_node: dict[str, list[EventRow]] = {}
    for row in rows:
        by_node.setdefault(str(row.node_id), []).append(row)
    folded = {node: _fold(node_rows, sinks) for node, node_rows in by_node.items()}
    return {node: alarms for node, alarms in folded.items() if alarms.all()}


def _sinks_of(session: Session, event_ids: list[uuid.UUID]) -> dict[uuid.UUID, set[str]]:
    sinks: dict[uuid.UUID, set[str]] = {}
    for chunk in _chunks(event_ids, 500):
        for event_id, sink in session.execute(
            select(DeliveryRow.event_id, DeliveryRow.sink).where(DeliveryRow.event_id.in_(chunk))
        ).all():
            sinks.setdefault(event_id, set()).add(sink)
    return sinks


def _chunks(items: list[uuid.UUID], size: int) -> Iterable[list[uuid.UUID]]:
    for start in range(0, len(items), size):
        yield items[start:start + size]


@dataclass
class _Fold:
    """Open alarms while the events are read in order."""

    single: dict[Alarm, OpenAlarm] = field(default_factory=dict)
    faults: dict[str, OpenAlarm] = field(default_factory=dict)  # sensor_fault event id -> its alarm


def _fold(rows: Iterable[EventRow], sinks: dict[uuid.UUID, set[str]]) -> NodeAlarms:
    state = _Fold()
    for row in rows:
        kind = EventKind(row.kind)
        if kind == EventKind.SENSOR_FAULT:
            state.faults[str(row.id)] = _opened(row, sinks)
        elif kind == EventKind.SENSOR_FAULT_CLEARED:
            state.faults.pop(str(row.payload.get("raised_event_id")), None)
        elif kind in RAISED_BY:
            alarm = RAISED_BY[kind]
            before = state.single.get(alarm)
            opened = _opened(row, sinks)
            if before is not None:  # escalated: the same alarm, raised again
                opened = replace(opened, alarm_id=before.alarm_id, raised_at=before.raised_at,
                                 sinks=before.sinks | opened.sinks)
            state.single[alarm] = opened
        else:
            state.single.pop(ENDED_BY[kind], None)
    return NodeAlarms(
        damage=state.single.get(Alarm.DAMAGE),
        blind=state.single.get(Alarm.BLIND),
        offline=state.single.get(Alarm.OFFLINE),
        sensor_faults=tuple(sorted(state.faults.values(), key=lambda a: a.rx_index or 0)),
    )


def _opened(row: EventRow, sinks: dict[uuid.UUID, set[str]]) -> OpenAlarm:
    payload = dict(row.payload)
    return OpenAlarm(
        alarm=RAISED_BY[EventKind(row.kind)],
        alarm_id=row.id,
        latest_event_id=row.id,
        raised_at=datetime.fromisoformat(payload["occurred_at"]),
        routing=Severity(payload.get("routing_severity") or row.severity),
        payload=payload,
        sinks=frozenset(sinks.get(row.id, ())),
    )


# ------------------------------------------------------------------ the events of a change (pure)
def alarm_events(
    settings: AlertingSettings,
    change: AlarmChange,
    alarms: NodeAlarms,
    *,
    node_id: str,
    from_state: str,
    to_state: str,
    measurement_id: int,
    peak_di: float | None,
    threshold: float | None,
    axial_mm: float | None,
    angle_deg: float | None,
    reason: str | None,
    occurred_at: datetime | None = None,
    region: Mapping[str, Any] | None = None,
) -> list[EventInput]:
    """The outbox events of ``change`` for the measurement stored as ``measurement_id``: the ends
    first (each to the sinks that had the alarm), then the raises. ``reason``: why the imaging
    abstained (a blind raise carries it)."""
    def event(kind: EventKind, **alarm: Any) -> EventInput:
        return alarm_state_event(
            settings, kind, node_id=node_id, from_state=from_state, to_state=to_state, measurement_id=measurement_id,
            peak_di=peak_di, threshold=threshold, axial_mm=axial_mm, angle_deg=angle_deg, occurred_at=occurred_at,
            region=region, **alarm,
        )

    events = []
    for end in change.ends:
        kind = EventKind.DAMAGE_CLEARED if end.alarm.alarm == Alarm.DAMAGE else EventKind.MONITORING_RESTORED
        events.append(event(kind, alarm_id=end.alarm.alarm_id, ended_by=end.ended_by(), routing=end.alarm.routing,
                            sinks=end_sinks(settings, end.alarm, end.alarm.routing)))
    if change.raise_damage:
        escalated = alarms.damage.alarm_id if alarms.damage is not None else None
        events.append(event(EventKind.DAMAGE_RAISED, alarm_id=escalated))
    if change.raise_blind:
        events.append(event(EventKind.MONITORING_BLIND, reason=reason))
    return events


def decommissioning_events(
    settings: AlertingSettings,
    alarms: NodeAlarms,
    *,
    node_id: str,
    state: str,
    decommissioned_at: datetime,
    by: str,
    reason: str,
) -> list[EventInput]:
    """The end of every open alarm of a node an admin decommissioned (pure): each alarm's own
    ending event, ``ended_by`` the decommissioning, to the sinks that had it."""
    events = []
    for end in decommissioning_ends(alarms, by=by, reason=reason):
        alarm = end.alarm
        sinks = end_sinks(settings, alarm, alarm.routing)
        if alarm.alarm in (Alarm.DAMAGE, Alarm.BLIND):
            kind = EventKind.DAMAGE_CLEARED if alarm.alarm == Alarm.DAMAGE else EventKind.MONITORING_RESTORED
            events.append(alarm_state_event(
                settings, kind, node_id=node_id, from_state=state, to_state=state, measurement_id=None,
                peak_di=None, threshold=None, occurred_at=decommissioned_at, alarm_id=alarm.alarm_id,
                ended_by=end.ended_by(), routing=alarm.routing, sinks=sinks,
            ))
        elif alarm.alarm == Alarm.OFFLINE:
            events.append(node_online_event(
                settings, node_id=node_id, state=state, offline_event_id=alarm.alarm_id,
                offline_since=datetime.fromisoformat(alarm.payload["last_seen_at"]), seen_at=decommissioned_at,
                ended_by=end.ended_by(), sinks=sinks,
            ))
        else:
            events.append(sensor_fault_cleared_event(
                settings, node_id=node_id, raised_event_id=alarm.alarm_id, raised_receiver=alarm.payload["receiver"],
                raised_measurement_id=alarm.payload.get("measurement_id"), measurement_id=None, state=state,
                faulty_receivers=[], consecutive=0, occurred_at=decommissioned_at, ended_by=end.ended_by(),
                sinks=sinks,
            ))
    return events
