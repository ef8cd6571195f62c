"""Nodes: registration from INFO replies, and the gateway's view of their health."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import NotFound
from db.models import NodeRow, NodeState
from db.records import NodeInfo


def get_node(session: Session, node_id: str) -> NodeRow:
    """The node called ``node_id``; raises :class:`NotFound`."""
    node = session.get(NodeRow, node_id)
    if node is None:
        raise NotFound(f"no node {node_id!r}")
    return node


def list_nodes(session: Session) -> Sequence[NodeRow]:
    """All nodes, ordered by node_id."""
    return session.scalars(select(NodeRow).order_by(NodeRow.node_id)).all()


def upsert_node(session: Session, info: NodeInfo, *, seen_at: datetime | None = None) -> NodeRow:
    """Create the node or refresh its configuration from a new INFO reply; marks it online.

    State, DI results and error counters of a known node are kept: a reboot does not make
    a damaged pipe healthy.
    """
    seen_at = seen_at or utc_now()
    node = session.get(NodeRow, info.node_id)
    if node is None:
        node = NodeRow(
            node_id=info.node_id,
            first_seen_at=seen_at,
            error_counters={},
            state=NodeState.COMMISSIONING,
        )
        session.add(node)
    node.port_url = info.port_url
    node.firmware = info.firmware
    node.protocol_version = info.protocol_version
    node.n_channels = info.n_channels
    node.fs_hz = info.fs_hz
    node.geometry = info.geometry.model_dump(mode="json")
    node.last_seen_at = seen_at
    node.online = True
    session.flush()
    return node


def record_node_health(
    session: Session,
    node_id: str,
    *,
    online: bool,
    error_counters: Mapping[str, int] | None = None,
    seen_at: datetime | None = None,
) -> NodeRow:
    """Store the result of a poll: online flag, the node's error counters, when it answered."""
    node = get_node(session, node_id)
    node.online = online
    if error_counters is not None:
        # A new dict, so the JSON column is seen as changed.
        node.error_counters = {str(name): int(count) for name, count in error_counters.items()}
    if online:
        node.last_seen_at = seen_at or utc_now()
    session.flush()
    return node
