"""The outbox in the database: finding due deliveries, claiming them crash-safely, recording results.

All delivery state lives in ``deliveries`` rows, so a killed daemon or a rebooted machine
loses nothing: a claim is a lease (``next_attempt_at`` pushed past the attempt's longest
possible duration, ``attempts`` incremented, committed before the request is sent); a
delivery is marked delivered only after the receiver acknowledged. A claim whose process
died simply becomes due again when its lease runs out — the event is then sent again
(at-least-once; receivers de-duplicate on the event id).

Also the read-side helpers for the API and ``/metrics``: counts per sink and status.
"""
from __future__ import annotations

import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, cast

from sqlalchemy import CursorResult, Result, func, or_, select, update
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.log_text import redact
from db.models import DeliveryRow, DeliveryStatus, EventRow, Severity


@dataclass(frozen=True)
class OutboxEvent:
    """One delivery to attempt: the event as the sink needs it, detached from any session."""

    delivery_id: int
    sink: str
    attempts: int  # tries started before this one
    next_attempt_at: datetime | None
    event_id: uuid.UUID
    node_id: str | None
    kind: str
    severity: Severity
    payload: dict[str, Any]
    created_at: datetime


def _outbox_event(delivery: DeliveryRow, event: EventRow) -> OutboxEvent:
    return OutboxEvent(
        delivery_id=delivery.id,
        sink=delivery.sink,
        attempts=delivery.attempts,
        next_attempt_at=delivery.next_attempt_at,
        event_id=event.id,
        node_id=event.node_id,
        kind=event.kind,
        severity=event.severity,
        payload=dict(event.payload),
        created_at=event.created_at,
    )


def pending_heads(session: Session, sink: str) -> list[OutboxEvent]:
    """The oldest pending delivery of each node for ``sink`` (due or not), oldest first.

    Only a node's head may be attempted: a later event for a node never overtakes an
    earlier one at the same sink. Events without a node form one group of their own.
    """
    return _first_per_node(
        session,
        (DeliveryRow.sink == sink, DeliveryRow.status == DeliveryStatus.PENDING),
        (EventRow.created_at, DeliveryRow.id),
    )


def is_due(item: OutboxEvent, now: datetime, *, horizon_s: float | None = None) -> bool:
    """Its time has come; or (``horizon_s``) its time lies further ahead than any wait the
    outbox sets: the wall clock was stepped back after the time was set, so it is due now."""
    at = item.next_attempt_at
    if at is None or at <= now:
        return True
    return horizon_s is not None and at > now + timedelta(seconds=horizon_s)


def claim(session: Session, item: OutboxEvent, *, now: datetime, lease_s: float, overdue: bool = False) -> bool:
    """Take ``item`` for one attempt (compare-and-set); False if it changed since it was read.

    ``overdue``: the caller knows it is due whatever its stored time says (a retry whose wait
    has passed on the monotonic clock, or a time beyond the horizon after a clock step).
    Commit the transaction before sending: the lease and the attempt count must be durable
    first, so a crash during the send neither loses the delivery nor retries it at once.
    """
    due = [] if overdue else [or_(DeliveryRow.next_attempt_at.is_(None), DeliveryRow.next_attempt_at <= now)]
    result = session.execute(
        update(DeliveryRow)
        .where(
            DeliveryRow.id == item.delivery_id,
            DeliveryRow.status == DeliveryStatus.PENDING,
            DeliveryRow.attempts == item.attempts,
            *due,
        )
        .values(attempts=DeliveryRow.attempts + 1, next_attempt_at=now + timedelta(seconds=lease_s))
        .execution_options(synchronize_session=False)
    )
    return _affected(result) == 1


def mark_delivered(session: Session, delivery_id: int) -> bool:
    """The receiver acknowledged: the delivery is done (False if it was no longer pending)."""
    result = session.execute(
        update(DeliveryRow)
        .where(DeliveryRow.id == delivery_id, DeliveryRow.status == DeliveryStatus.PENDING)
        .values(status=DeliveryStatus.DELIVERED, next_attempt_at=None, last_error=None)
        .execution_options(synchronize_session=False)
    )
    return _affected(result) == 1


def mark_failed(session: Session, delivery_id: int, error: str, *, retry_at: datetime | None) -> bool:
    """Record a failed attempt: retry at ``retry_at``, or dead when it is None."""
    values: dict[str, Any] = {"last_error": redact(error)[:2000]}  # shown by the API: no credentials
    if retry_at is None:
        values.update(status=DeliveryStatus.DEAD, next_attempt_at=None)
    else:
        values.update(next_attempt_at=retry_at)
    result = session.execute(
        update(DeliveryRow)
        .where(DeliveryRow.id == delivery_id, DeliveryRow.status == DeliveryStatus.PENDING)
        .values(**values)
        .execution_options(synchronize_session=False)
    )
    return _affected(result) == 1


def kill_pending(session: Session, sink: str, reason: str) -> int:
    """Mark every pending delivery of ``sink`` dead (the sink is disabled); returns how many."""
    result = session.execute(
        update(DeliveryRow)
        .where(DeliveryRow.sink == sink, DeliveryRow.status == DeliveryStatus.PENDING)
        .values(status=DeliveryStatus.DEAD, next_attempt_at=None, last_error=redact(reason)[:2000])
        .execution_options(synchronize_session=False)
    )
    return _affected(result)


def latest_delivered(session: Session, sink: str, kinds: Iterable[str]) -> list[OutboxEvent]:
    """Per node, the newest event of ``kinds`` delivered to ``sink`` (what the receiver last heard)."""
    return _first_per_node(
        session,
        (
            DeliveryRow.sink == sink,
            DeliveryRow.status == DeliveryStatus.DELIVERED,
            EventRow.kind.in_([str(k) for k in kinds]),
        ),
        (EventRow.created_at.desc(), DeliveryRow.id.desc()),
    )


def delivered_events(session: Session, sink: str, kinds: Iterable[str]) -> list[OutboxEvent]:
    """Every event of ``kinds`` delivered to ``sink``, oldest first (for kinds that are rare: transitions)."""
    rows = session.execute(
        select(DeliveryRow, EventRow)
        .join(EventRow, EventRow.id == DeliveryRow.event_id)
        .where(
            DeliveryRow.sink == sink,
            DeliveryRow.status == DeliveryStatus.DELIVERED,
            EventRow.kind.in_([str(k) for k in kinds]),
        )
        .order_by(EventRow.created_at, DeliveryRow.id)
    ).all()
    return [_outbox_event(delivery, event) for delivery, event in rows]


def _first_per_node(session: Session, where: tuple, order_by: tuple) -> list[OutboxEvent]:
    """Of the deliveries matching ``where``, the first of each node in ``order_by``, oldest event first."""
    rank = func.row_number().over(partition_by=EventRow.node_id, order_by=order_by).label("rank")
    ranked = (
        select(DeliveryRow.id.label("delivery_id"), rank)
        .join(EventRow, EventRow.id == DeliveryRow.event_id)
        .where(*where)
        .subquery()
    )
    rows = session.execute(
        select(DeliveryRow, EventRow)
        .join(EventRow, EventRow.id == DeliveryRow.event_id)
        .join(ranked, ranked.c.delivery_id == DeliveryRow.id)
        .where(ranked.c.rank == 1)
        .order_by(EventRow.created_at, DeliveryRow.id)
    ).all()
    return [_outbox_event(delivery, event) for delivery, event in rows]


def events_of_kind(session: Session, kind: str, *, node_id: str | None = None, newest_first: bool = True) -> Sequence[EventRow]:
    """Events of one kind (optionally of one node), newest first unless told otherwise."""
    query = select(EventRow).where(EventRow.kind == str(kind))
    if node_id is not None:
        query = query.where(EventRow.node_id == node_id)
    order = (EventRow.created_at.desc(), EventRow.id.desc()) if newest_first else (EventRow.created_at, EventRow.id)
    return session.scalars(query.order_by(*order)).all()


# ------------------------------------------------------------------ read side (API, /metrics)
def delivery_counts(session: Session) -> dict[tuple[str, DeliveryStatus], int]:
    """Number of deliveries per (sink, status); absent pairs are zero."""
    rows = session.execute(
        select(DeliveryRow.sink, DeliveryRow.status, func.count()).group_by(DeliveryRow.sink, DeliveryRow.status)
    ).all()
    return {(sink, DeliveryStatus(status)): int(n) for sink, status, n in rows}


def dead_count(session: Session, sink: str | None = None) -> int:
    """Deliveries given up on (all sinks, or one)."""
    return _count(session, DeliveryStatus.DEAD, sink)


def pending_count(session: Session, sink: str | None = None) -> int:
    """Deliveries not yet acknowledged (all sinks, or one)."""
    return _count(session, DeliveryStatus.PENDING, sink)


def _count(session: Session, status: DeliveryStatus, sink: str | None) -> int:
    query = select(func.count()).select_from(DeliveryRow).where(DeliveryRow.status == status)
    if sink is not None:
        query = query.where(DeliveryRow.sink == sink)
    return int(session.scalar(query) or 0)


def oldest_pending_age_s(session: Session, *, now: datetime | None = None) -> dict[str, float]:
    """Per sink, how long its oldest pending event has waited (seconds); sinks with none are absent."""
    now = now or utc_now()
    rows = session.execute(
        select(DeliveryRow.sink, func.min(EventRow.created_at))
        .join(EventRow, EventRow.id == DeliveryRow.event_id)
        .where(DeliveryRow.status == DeliveryStatus.PENDING)
        .group_by(DeliveryRow.sink)
    ).all()
    result = {}
    for sink, oldest in rows:
        oldest = _aware(oldest)
        result[sink] = max(0.0, (now - oldest).total_seconds())
    return result


def _aware(value: datetime | str) -> datetime:
    # In case min() over the column comes back untyped (naive UTC text on SQLite).
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def _affected(result: Result[Any]) -> int:
    """Rows an UPDATE matched: its result is a CursorResult, which the ORM's typing does not say."""
    return cast(CursorResult[Any], result).rowcount
