"""Alerts: the gateway's outbox events, with an operator's acknowledgement and resolution."""
from __future__ import annotations

import base64
import binascii
import json
import uuid
from datetime import UTC, datetime

from sqlalchemy import and_, or_, select
from sqlalchemy.orm import Session, selectinload

from db.clock import utc_now
from db.errors import InvalidCursor, NotFound
from db.models import EventRow, Severity
from db.pagination import MALFORMED_CURSOR, MAX_PAGE_SIZE
from service import schemas


def _status(row: EventRow) -> schemas.AlertStatus:
    if row.resolved_at is not None:
        return schemas.AlertStatus.RESOLVED
    if row.acknowledged_at is not None:
        return schemas.AlertStatus.ACKNOWLEDGED
    return schemas.AlertStatus.OPEN


def alert_view(row: EventRow) -> schemas.Alert:
    return schemas.Alert(
        id=row.id,
        node_id=row.node_id,
        kind=row.kind,
        severity=row.severity,
        payload=row.payload,
        created_at=row.created_at,
        status=_status(row),
        acknowledged_at=row.acknowledged_at,
        acknowledged_by=row.acknowledged_by,
        resolved_at=row.resolved_at,
        resolved_by=row.resolved_by,
        deliveries=[schemas.Delivery.model_validate(d) for d in row.deliveries],
    )


def _encode_cursor(row: EventRow) -> str:
    payload = json.dumps({"t": row.created_at.isoformat(), "id": str(row.id)}, separators=(",", ":"))
    return base64.urlsafe_b64encode(payload.encode()).decode().rstrip("=")


def _decode_cursor(cursor: str) -> tuple[datetime, uuid.UUID]:
    try:
        payload = json.loads(base64.urlsafe_b64decode((cursor + "=" * (-len(cursor) % 4)).encode("ascii")))
        at = datetime.fromisoformat(payload["t"])
        event_id = uuid.UUID(payload["id"])
        if at.tzinfo is None or at.utcoffset() is None:
            raise InvalidCursor(MALFORMED_CURSOR)
        at = at.astimezone(UTC)
    except InvalidCursor:
        raise
    except (ValueError, KeyError, TypeError, UnicodeError, binascii.Error, AttributeError, OverflowError,
            RecursionError):
        raise InvalidCursor(MALFORMED_CURSOR) from None
    return at, event_id


def alert_list(
    session: Session,
    *,
    status: schemas.AlertStatus | None,
    node_id: str | None,
    severity: Severity | None,
    limit: int,
    cursor: str | None,
) -> schemas.AlertPage:
    """Alerts newest first, keyset-paged on (created_at, id)."""
    if not 1 <= limit <= MAX_PAGE_SIZE:
        raise ValueError(f"page size must be 1..{MAX_PAGE_SIZE}")
    statement = select(EventRow).options(selectinload(EventRow.deliveries))
    if status == schemas.AlertStatus.OPEN:
        statement = statement.where(EventRow.acknowledged_at.is_(None), EventRow.resolved_at.is_(None))
    elif status == schemas.AlertStatus.ACKNOWLEDGED:
        statement = statement.where(EventRow.acknowledged_at.is_not(None), EventRow.resolved_at.is_(None))
    elif status == schemas.AlertStatus.RESOLVED:
        statement = statement.where(EventRow.resolved_at.is_not(None))
    if node_id is not None:
        statement = statement.where(EventRow.node_id == node_id)
    if severity is not None:
        statement = statement.where(EventRow.severity == severity)
    if cursor is not None:
        at, event_id = _decode_cursor(cursor)
        statement = statement.where(
            or_(EventRow.created_at < at, and_(EventRow.created_at == at, EventRow.id < event_id))
        )
    rows = list(session.scalars(statement.order_by(EventRow.created_at.desc(), EventRow.id.desc()).limit(limit + 1)))
    next_cursor = _encode_cursor(rows[limit - 1]) if len(rows) > limit else None
    return schemas.AlertPage(items=[alert_view(r) for r in rows[:limit]], next_cursor=next_cursor)


def _event(session: Session, alert_id: uuid.UUID) -> EventRow:
    row = session.get(EventRow, alert_id)
    if row is None:
        raise NotFound(f"no alert {alert_id}")
    return row


def get_alert(session: Session, alert_id: uuid.UUID) -> schemas.Alert:
    return alert_view(_event(session, alert_id))


def acknowledge(session: Session, alert_id: uuid.UUID, *, who: str) -> schemas.Alert:
    """Mark the alert seen (idempotent: the first acknowledgement is kept). Call in a write transaction."""
    row = _event(session, alert_id)
    if row.acknowledged_at is None:
        row.acknowledged_at = utc_now()
        row.acknowledged_by = who
        session.flush()
    return alert_view(row)


def resolve(session: Session, alert_id: uuid.UUID, *, who: str) -> schemas.Alert:
    """Close the alert (idempotent); an unacknowledged alert is acknowledged by the same caller."""
    row = _event(session, alert_id)
    now = utc_now()
    if row.acknowledged_at is None:
        row.acknowledged_at, row.acknowledged_by = now, who
    if row.resolved_at is None:
        row.resolved_at, row.resolved_by = now, who
    session.flush()
    return alert_view(row)
