"""baseline_changed events for every new baseline row, whoever set it (gateway commissioning, API operator).

Read from the ``baselines`` history, so the API needs no alerting config and nothing is
missed while the gateway is down; the event id is a function of the baseline row, so a row
gets one event however often it is checked. Only rows newer than ``lookback`` are looked
at, which bounds the work and keeps a first start on an old database quiet.
"""
from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from alerts.config import AlertingSettings
from alerts.events import baseline_changed_event
from db.measurements import add_event_once
from db.models import BaselineRow, NodeRow
from db.records import EventInput

DEFAULT_LOOKBACK = timedelta(days=7)


def check_baseline_changes(
    session: Session, settings: AlertingSettings, *, now: datetime, lookback: timedelta = DEFAULT_LOOKBACK
) -> list[EventInput]:
    """Put a baseline_changed event in the outbox for each recent baseline without one (call in ``write()``)."""
    added = []
    recent = session.scalars(
        select(BaselineRow).where(BaselineRow.created_at >= now - lookback).order_by(BaselineRow.id)
    ).all()
    for baseline in recent:
        previous = session.scalars(
            select(BaselineRow.measurement_id)
            .where(BaselineRow.node_id == baseline.node_id, BaselineRow.id < baseline.id)
            .order_by(BaselineRow.id.desc())
            .limit(1)
        ).first()
        node = session.get(NodeRow, baseline.node_id)
        event = baseline_changed_event(
            settings,
            node_id=baseline.node_id,
            baseline_id=baseline.id,
            measurement_id=baseline.measurement_id,
            previous_measurement_id=previous,
            created_by=baseline.created_by,
            reason=baseline.reason,
            state=node.state.value if node is not None else "unknown",
            occurred_at=baseline.created_at,
        )
        if add_event_once(session, event, node_id=baseline.node_id, now=now):
            added.append(event)
    return added
