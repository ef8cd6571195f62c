"""Nodes: registration from INFO replies, the gateway's view of their health, and what an
admin decides about them (label, location, notes; decommissioning).

Every change of what a node's uplink record carries beyond its health (an INFO, an admin's
details, (re)commissioning) raises ``revision`` and, when the database queues for an uplink,
queues the node's record in the same transaction (``db.uplink_queue``)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import NotFound, StateConflict
from db.models import NodeRow, NodeState
from db.records import NodeInfo
from db.uplink_queue import enqueue_node, enqueue_node_change, queue_policy


def get_node(session: Session, node_id: str) -> NodeRow:
    """The node called ``node_id``; raises :class:`NotFound`."""
    node = session.get(NodeRow, node_id)
    if node is None:
        raise NotFound(f"no node {node_id!r}")
    return node


def list_nodes(session: Session, *, include_decommissioned: bool = True) -> Sequence[NodeRow]:
    """All nodes (or only those in service), ordered by node_id."""
    statement = select(NodeRow).order_by(NodeRow.node_id)
    if not include_decommissioned:
        statement = statement.where(NodeRow.decommissioned_at.is_(None))
    return session.scalars(statement).all()


# The fields update_node_details may set (an admin, through the API); any other is refused.
NODE_DETAILS = ("label", "location", "notes")


def update_node_details(
    session: Session, node_id: str, changes: Mapping[str, str | None], *, who: str, now: datetime | None = None
) -> NodeRow:
    """Set some of the node's label, location and notes (None clears one); records who and when."""
    unknown = set(changes) - set(NODE_DETAILS)
    if unknown:
        raise ValueError(f"not node details: {sorted(unknown)}")
    node = get_node(session, node_id)
    for name, value in changes.items():
        setattr(node, name, value)
    node.details_updated_at = now or utc_now()
    node.details_updated_by = who
    return _admin_changed(session, node, now=node.details_updated_at)


def decommission_node(
    session: Session, node_id: str, *, who: str, reason: str, now: datetime | None = None
) -> NodeRow:
    """Take the node out of service: the gateway stops polling it, no outage alert is raised for it.

    Its history stays. Raises :class:`StateConflict` if it is decommissioned already (the
    first decision, with its who and why, is kept).
    """
    node = get_node(session, node_id)
    if node.decommissioned_at is not None:
        raise StateConflict(
            f"node {node_id!r} was decommissioned at {node.decommissioned_at.isoformat()} by {node.decommissioned_by}"
        )
    node.decommissioned_at = now or utc_now()
    node.decommissioned_by = who
    node.decommission_reason = reason
    node.online = False  # the gateway lets go of it
    return _admin_changed(session, node, now=node.decommissioned_at)


def recommission_node(session: Session, node_id: str, *, now: datetime | None = None) -> NodeRow:
    """Put a decommissioned node back in service; raises :class:`StateConflict` if it is in service.

    The gateway watches it again from now (``watched_since``): a node silent since before its
    decommissioning gets ``offline_after_s`` to answer before it is reported offline, like a node
    at the gateway's start (alerts/outages.py)."""
    node = get_node(session, node_id)
    if node.decommissioned_at is None:
        raise StateConflict(f"node {node_id!r} is in service")
    node.decommissioned_at = node.decommissioned_by = node.decommission_reason = None
    node.watched_since = now or utc_now()
    return _admin_changed(session, node, now=node.watched_since)


def _admin_changed(session: Session, node: NodeRow, *, now: datetime | None) -> NodeRow:
    """An admin changed what the node's record carries: a new revision, queued for the uplink."""
    node.revision += 1
    session.flush()
    enqueue_node_change(session, node.node_id, now=now)
    return node


def decommissioned_node_ids(session: Session) -> set[str]:
    """The nodes an admin has taken out of service."""
    return set(session.scalars(select(NodeRow.node_id).where(NodeRow.decommissioned_at.is_not(None))))


def is_decommissioned(session: Session, node_id: str) -> bool:
    """True for a known node an admin has decommissioned (an unknown node is not)."""
    decommissioned_at = session.scalar(select(NodeRow.decommissioned_at).where(NodeRow.node_id == node_id))
    return decommissioned_at is not None


def register_configured_node(session: Session, node_id: str, *, port_url: str, now: datetime | None = None) -> bool:
    """Register a node of the gateway's configuration that this database does not know yet: watched
    from ``now``, never seen, what INFO tells unknown until it answers; True if it was new.

    Nothing is queued for the uplink: the centre is told of a node by its first INFO (upsert_node).
    A known node is left as it is (its port, as last found, comes with its INFO).
    """
    if session.get(NodeRow, node_id) is not None:
        return False
    session.add(NodeRow(
        node_id=node_id, port_url=port_url, watched_since=now or utc_now(), online=False, error_counters={},
        state=NodeState.COMMISSIONING,
    ))
    session.flush()
    return True


def upsert_node(session: Session, info: NodeInfo, *, seen_at: datetime | None = None) -> NodeRow:
    """Create the node or refresh its configuration from a new INFO reply; marks it online.

    State, DI results and error counters of a known node are kept: a reboot does not make
    a damaged pipe healthy; a node registered from the configuration and never seen is seen
    first now. A session that queues for the uplink queues the node's record.
    """
    seen_at = seen_at or utc_now()
    node = session.get(NodeRow, info.node_id)
    if node is None:
        node = NodeRow(
            node_id=info.node_id,
            watched_since=seen_at,
            error_counters={},
            state=NodeState.COMMISSIONING,
        )
        session.add(node)
    first_answer = node.first_seen_at is None
    if first_answer:
        node.first_seen_at = seen_at
    node.port_url = info.port_url
    node.firmware = info.firmware
    node.protocol_version = info.protocol_version
    node.n_channels = info.n_channels
    node.fs_hz = info.fs_hz
    node.geometry = info.geometry.model_dump(mode="json")
    node.last_seen_at = seen_at
    node.online = True
    node.revision = (node.revision or 0) + 1
    session.flush()
    if queue_policy(session) is not None:
        enqueue_node(session, info.node_id, now=seen_at, first_answer=first_answer)
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


def record_node_link(
    session: Session,
    node_id: str,
    *,
    reported_node_id: str,
    boot_id: int,
    applied_settings: Mapping[str, float | int] | None,
    problems: Sequence[str],
    rebooted: bool = False,
    seen_at: datetime | None = None,
) -> NodeRow:
    """Store what the gateway found on the node's port at (re)connection: who answers, its boot,
    the settings it applied and how it differs from the configuration; ``rebooted`` counts a
    reboot the gateway noticed (a new boot id on an open port)."""
    node = get_node(session, node_id)
    node.reported_node_id = reported_node_id
    node.boot_id = boot_id
    node.applied_settings = None if applied_settings is None else dict(applied_settings)
    node.link_problems = list(problems)
    if rebooted:
        node.reboots = (node.reboots or 0) + 1
        node.last_reboot_at = seen_at or utc_now()
    session.flush()
    return node
