"""Sensor fault alerts: sensor_fault when a receiver turns faulty, sensor_fault_cleared when it recovers.

The imaging judges each receiver of every monitor measurement (``imaging/health.py``); the
verdict is stored with the measurement (``detections.sensor_faults``). An alert is raised on
transitions only, with hysteresis like the damage flagging: a receiver faulty in
``sensor_fault_count`` consecutive measurements raises ``sensor_fault``; once raised, it
takes as many consecutive healthy measurements to raise ``sensor_fault_cleared``. A receiver
that flaps in between neither raises nor clears.

Nothing is kept in memory: the recent verdicts are the node's last detections and what is
raised is read from the outbox (a ``sensor_fault`` event no ``sensor_fault_cleared`` points
back to), both written in the transaction of the measurement. So a gateway restart neither
raises a fault again nor loses a clearing, and a crash before the commit loses the
measurement and its events together (the next measurement decides again).
"""
from __future__ import annotations

import uuid
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from alerts.config import AlertingSettings
from alerts.events import EventKind, sensor_fault_cleared_event, sensor_fault_event
from db.measurements import add_event_once
from db.models import EventRow
from db.queries import recent_sensor_faults
from db.records import EventInput


@dataclass(frozen=True)
class ReceiverTransitions:
    """Receivers (rx_index) whose alert changes with this measurement."""

    raised: tuple[int, ...] = ()
    cleared: tuple[int, ...] = ()


def receiver_transitions(recent: Sequence[Collection[int]], open_faults: Collection[int], count: int) -> ReceiverTransitions:
    """Which receivers raise and which clear, after the newest measurement.

    ``recent``: the faulty receivers of the node's latest measurements, oldest first, the one
    just taken last; ``open_faults``: receivers with a raised, not yet cleared alert;
    ``count``: consecutive measurements needed (``AlertingSettings.sensor_fault_count``).
    A receiver raises when it is faulty in each of the last ``count`` measurements and not
    open; an open one clears when it is faulty in none of them. Fewer than ``count``
    measurements decide nothing.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    window = [set(faulty) for faulty in recent[-count:]]
    if len(window) < count:
        return ReceiverTransitions()
    always = set.intersection(*window)
    ever = set.union(*window)
    opened = set(open_faults)
    return ReceiverTransitions(raised=tuple(sorted(always - opened)), cleared=tuple(sorted(opened - ever)))


@dataclass(frozen=True)
class OpenFault:
    """A receiver's raised sensor_fault event that no clearing has ended yet."""

    event_id: uuid.UUID
    receiver: dict[str, Any]
    measurement_id: int | None


@dataclass(frozen=True)
class SensorFaultHistory:
    """What a node's next sensor-fault decision depends on, read before its measurement is stored."""

    count: int  # consecutive measurements to raise or clear (``AlertingSettings.sensor_fault_count``)
    earlier: tuple[dict[int, dict[str, Any]], ...]  # faulty receivers of the last count - 1 verdicts, oldest first
    open_faults: dict[int, OpenFault]


@dataclass(frozen=True)
class SensorFaultChange:
    """The receivers whose alert a measurement raises or clears, with what their events need."""

    raised: tuple[dict[str, Any], ...] = ()  # this measurement's fault of each receiver that raises
    cleared: tuple[OpenFault, ...] = ()  # the open alert of each receiver that clears
    faulty_after: tuple[int, ...] = ()  # receivers with an open alert once this measurement is stored
    consecutive: int = 0

    def __bool__(self) -> bool:
        return bool(self.raised or self.cleared)


def sensor_fault_history(
    session: Session, node_id: str, count: int, *, exclude_measurement_id: int | None = None
) -> SensorFaultHistory:
    """The node's recent verdicts and open sensor-fault alerts (``exclude_measurement_id``: one already stored)."""
    earlier = recent_sensor_faults(session, node_id, limit=count - 1, exclude_measurement_id=exclude_measurement_id)
    return SensorFaultHistory(count, tuple(_by_receiver(f) for f in reversed(earlier)), open_sensor_faults(session, node_id))


def sensor_fault_change(history: SensorFaultHistory, faults: Sequence[dict[str, Any]] | None) -> SensorFaultChange:
    """Which receivers raise and which clear with a measurement whose sensor faults are ``faults`` (pure)."""
    current = _by_receiver(faults)
    recent = [set(f) for f in history.earlier] + [set(current)]
    open_faults = history.open_faults
    change = receiver_transitions(recent, open_faults, history.count)
    if not change.raised and not change.cleared:
        return SensorFaultChange()
    return SensorFaultChange(
        raised=tuple(current[rx] for rx in change.raised),
        cleared=tuple(open_faults[rx] for rx in change.cleared),
        faulty_after=tuple(sorted((set(open_faults) | set(change.raised)) - set(change.cleared))),
        consecutive=history.count,
    )


def sensor_fault_events(
    settings: AlertingSettings,
    change: SensorFaultChange,
    *,
    node_id: str,
    measurement_id: int,
    state: str,
    now: datetime | None = None,
) -> list[EventInput]:
    """The sensor_fault / sensor_fault_cleared events of ``change`` for the stored measurement (pure)."""
    faulty_after = list(change.faulty_after)
    return [
        sensor_fault_event(
            settings, node_id=node_id, fault=fault, measurement_id=measurement_id, state=state,
            faulty_receivers=faulty_after, consecutive=change.consecutive, occurred_at=now,
        )
        for fault in change.raised
    ] + [
        sensor_fault_cleared_event(
            settings, node_id=node_id, raised_event_id=open_fault.event_id, raised_receiver=open_fault.receiver,
            raised_measurement_id=open_fault.measurement_id, measurement_id=measurement_id, state=state,
            faulty_receivers=faulty_after, consecutive=change.consecutive, occurred_at=now,
        )
        for open_fault in change.cleared
    ]


def check_sensor_faults(
    session: Session,
    settings: AlertingSettings,
    *,
    node_id: str,
    measurement_id: int,
    faults: Sequence[dict[str, Any]] | None,
    state: str,
    now: datetime | None = None,
) -> list[EventInput]:
    """Put the sensor_fault / sensor_fault_cleared events this measurement causes in the outbox.

    Call in the ``Database.write()`` transaction that stored the measurement (its detection
    with ``faults`` = ``detections.sensor_faults``), after ``store_measurement``; returns
    the events added. (The gateway reads the history before it stores, and adds the events
    of ``sensor_fault_change`` with the measurement: the same decision.)
    """
    history = sensor_fault_history(
        session, node_id, settings.sensor_fault_count, exclude_measurement_id=measurement_id
    )
    change = sensor_fault_change(history, faults)
    events = sensor_fault_events(settings, change, node_id=node_id, measurement_id=measurement_id, state=state, now=now)
    return [event for event in events if add_event_once(session, event, node_id=node_id, now=now)]


def open_sensor_faults(session: Session, node_id: str) -> dict[int, OpenFault]:
    """Per receiver (rx_index), the node's sensor_fault event not yet followed by its clearing."""
    return open_sensor_faults_by_node(session, node_id).get(node_id, {})


def open_sensor_faults_by_node(session: Session, node_id: str | None = None) -> dict[str, dict[int, OpenFault]]:
    """The open sensor faults of every node (or of one): node -> rx_index -> its sensor_fault event."""
    query = select(EventRow).where(
        EventRow.kind.in_([str(EventKind.SENSOR_FAULT), str(EventKind.SENSOR_FAULT_CLEARED)])
    )
    if node_id is not None:
        query = query.where(EventRow.node_id == node_id)
    rows = session.scalars(query.order_by(EventRow.created_at, EventRow.id)).all()
    cleared = {str(r.payload.get("raised_event_id")) for r in rows if r.kind == EventKind.SENSOR_FAULT_CLEARED}
    open_faults: dict[str, dict[int, OpenFault]] = {}
    for row in rows:
        if row.kind == EventKind.SENSOR_FAULT and str(row.id) not in cleared and row.node_id is not None:
            receiver = row.payload["receiver"]
            open_faults.setdefault(row.node_id, {})[int(receiver["rx_index"])] = OpenFault(
                row.id, receiver, row.payload.get("measurement_id")
            )
    return open_faults


def _by_receiver(faults: Sequence[dict[str, Any]] | None) -> dict[int, dict[str, Any]]:
    """A measurement's stored sensor faults by rx_index (None, as on rows without a verdict: none)."""
    try:
        return {int(f["rx_index"]): f for f in faults or ()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"sensor faults must be a list of objects with an integer rx_index, got {faults!r}") from exc
