"""Node reachability alerts: node_offline after ``offline_after_s`` without an answer, node_online after.

Everything is read from the database (``nodes.last_seen_at``, or ``nodes.watched_since`` for a
node that never answered, and the outage events already in the outbox), so the check is
idempotent and survives restarts: an outage keeps its one event id however often it is checked.
Right after the gateway starts, nodes are given ``offline_after_s`` to answer before the
downtime of the gateway itself counts against them; so is a node an admin has just recommissioned
(``nodes.watched_since``), which may have been silent since long before.
"""
from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from alerts.config import AlertingSettings
from alerts.events import OUTAGE_KINDS, EventKind, node_offline_event, node_online_event
from db.measurements import add_event_once
from db.models import EventRow
from db.nodes import list_nodes
from db.records import EventInput


def check_outages(
    session: Session, settings: AlertingSettings, *, now: datetime, watching_since: datetime
) -> list[EventInput]:
    """Put node_offline/node_online events in the outbox where a node's reachability changed.

    Call inside ``Database.write()``; returns the events added.
    """
    added = []
    # A decommissioned node is not polled: its silence is intended, not an outage.
    for node in list_nodes(session, include_decommissioned=False):
        latest = _latest_outage_event(session, node.node_id)
        open_outage = latest if latest is not None and latest.kind == EventKind.NODE_OFFLINE else None
        if open_outage is None:
            silent_since = silent_since_of(node.last_seen_at, node.watched_since)
            # Counted from the gateway's start, or from the node's recommissioning, at the earliest.
            watched = max(watching_since, node.watched_since)
            if not offline_due(silent_since, watched, now=now, offline_after_s=settings.offline_after_s):
                continue
            event = node_offline_event(
                settings, node_id=node.node_id, state=node.state.value, last_seen_at=silent_since, now=now,
                after=_ended_by_decommissioning(latest, silent_since), never_seen=node.never_seen,
            )
        else:
            offline_since = datetime.fromisoformat(open_outage.payload["last_seen_at"])
            if node.last_seen_at is None or node.last_seen_at <= offline_since:
                continue
            event = node_online_event(
                settings,
                node_id=node.node_id,
                state=node.state.value,
                offline_event_id=open_outage.id,
                offline_since=offline_since,
                seen_at=node.last_seen_at,
                first_seen=bool(open_outage.payload.get("never_seen")),
            )
        if add_event_once(session, event, node_id=node.node_id, now=now):
            added.append(event)
    return added


def silent_since_of(last_seen_at: datetime | None, watched_since: datetime) -> datetime:
    """Since when the node has been silent: its last answer, or, never seen, since it was watched (pure)."""
    return watched_since if last_seen_at is None else last_seen_at


def offline_due(silent_since: datetime, watching_since: datetime, *, now: datetime, offline_after_s: float) -> bool:
    """Whether a node silent since ``silent_since`` is offline at ``now`` (pure): silent for longer than
    ``offline_after_s``, counted from the gateway's start at the earliest (``watching_since``)."""
    return (now - max(silent_since, watching_since)).total_seconds() > offline_after_s


def _latest_outage_event(session: Session, node_id: str) -> EventRow | None:
    """The node's newest outage event (a node_offline not yet followed by node_online: an open outage)."""
    return session.scalars(
        select(EventRow)
        .where(EventRow.node_id == node_id, EventRow.kind.in_([str(k) for k in OUTAGE_KINDS]))
        .order_by(EventRow.created_at.desc(), EventRow.id.desc())
        .limit(1)
    ).first()


def _ended_by_decommissioning(latest: EventRow | None, last_seen_at: datetime) -> uuid.UUID | None:
    """The id of the end of an offline alarm over the same silence, when a decommissioning ended it
    (the node, recommissioned, is still silent: a new alarm, not the old one again)."""
    if latest is None or latest.kind != EventKind.NODE_ONLINE:
        return None
    ended_by = latest.payload.get("ended_by") or {}
    if ended_by.get("cause") != "decommissioning" or latest.payload.get("offline_since") != last_seen_at.isoformat():
        return None
    return latest.id
