"""Fleet-wide questions with site and gateway as attributes: which nodes, in what state, where, since when.

Central mode: nodes ingested from gateways carry their ``site`` and ``gateway_id``; a gateway's
own nodes have neither (``site`` None, reported as the local site). Every query is a bounded
number of statements whatever the fleet size; node lists are keyset-paged by node id.
"""
from __future__ import annotations

import base64
import binascii
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy import case, func, select
from sqlalchemy.orm import Session

from db.errors import InvalidCursor
from db.models import NodeRow, NodeState, StateChangeRow

FLAGGED = (NodeState.DAMAGE, NodeState.SUSPECTED)


@dataclass
class SiteSummary:
    site: str | None  # None: nodes without a site (a gateway's own)
    gateways: list[str] = field(default_factory=list)
    nodes: int = 0
    offline: int = 0
    by_state: dict[str, int] = field(default_factory=dict)
    last_seen_at: datetime | None = None

    @property
    def flagged(self) -> int:
        return sum(self.by_state.get(state.value, 0) for state in FLAGGED)


def site_summaries(session: Session) -> list[SiteSummary]:
    """One summary per site of the nodes in service, the sites with flagged nodes first, then by name."""
    rows = session.execute(
        select(NodeRow.site, NodeRow.gateway_id, NodeRow.state, func.count(),
               func.sum(case((NodeRow.online.is_(False), 1), else_=0)), func.max(NodeRow.last_seen_at))
        .where(NodeRow.decommissioned_at.is_(None))
        .group_by(NodeRow.site, NodeRow.gateway_id, NodeRow.state)
    ).all()
    sites: dict[str | None, SiteSummary] = {}
    for site, gateway, state, count, offline, last_seen in rows:
        summary = sites.setdefault(site, SiteSummary(site))
        if gateway is not None and gateway not in summary.gateways:
            summary.gateways.append(gateway)
        summary.nodes += count
        summary.offline += int(offline or 0)
        summary.by_state[state.value] = summary.by_state.get(state.value, 0) + count
        if last_seen is not None and (summary.last_seen_at is None or last_seen > summary.last_seen_at):
            summary.last_seen_at = last_seen
    for summary in sites.values():
        summary.gateways.sort()
    return sorted(sites.values(), key=lambda s: (-s.flagged, s.site is not None, s.site or ""))


def encode_node_cursor(node_id: str) -> str:
    return base64.urlsafe_b64encode(node_id.encode()).decode().rstrip("=")


def decode_node_cursor(cursor: str) -> str:
    try:
        return base64.urlsafe_b64decode((cursor + "=" * (-len(cursor) % 4)).encode("ascii")).decode()
    except (ValueError, UnicodeError, binascii.Error) as error:
        raise InvalidCursor(f"malformed cursor: {error}") from error


def fleet_node_page(
    session: Session,
    *,
    site: str | None = None,
    gateway_id: str | None = None,
    states: Sequence[NodeState] = (),
    limit: int = 50,
    cursor: str | None = None,
) -> tuple[list[NodeRow], str | None]:
    """One page of the nodes in service matching the filters, by node id, and the next page's cursor."""
    statement = select(NodeRow).where(NodeRow.decommissioned_at.is_(None)).order_by(NodeRow.node_id).limit(limit + 1)
    if site is not None:
        statement = statement.where(NodeRow.site == site)
    if gateway_id is not None:
        statement = statement.where(NodeRow.gateway_id == gateway_id)
    if states:
        statement = statement.where(NodeRow.state.in_(list(states)))
    if cursor is not None:
        statement = statement.where(NodeRow.node_id > decode_node_cursor(cursor))
    rows = list(session.scalars(statement))
    more = len(rows) > limit
    rows = rows[:limit]
    return rows, encode_node_cursor(rows[-1].node_id) if more and rows else None


def state_since(session: Session, nodes: Sequence[NodeRow]) -> dict[str, datetime]:
    """Since when each node is in its current state: its latest change into that state (absent: never changed)."""
    if not nodes:
        return {}
    rows = session.execute(
        select(StateChangeRow.node_id, StateChangeRow.to_state, func.max(StateChangeRow.at))
        .where(StateChangeRow.node_id.in_([n.node_id for n in nodes]))
        .group_by(StateChangeRow.node_id, StateChangeRow.to_state)
    ).all()
    latest = {(node_id, state): at for node_id, state, at in rows}
    return {n.node_id: latest[(n.node_id, n.state)] for n in nodes if (n.node_id, n.state) in latest}
