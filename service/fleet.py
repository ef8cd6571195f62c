"""The fleet as operators see it: each node's identity, health, state, baseline and latest verdict."""
from __future__ import annotations

import logging
from collections.abc import Sequence

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db import fleet_queries
from db.models import BaselineRow, DetectionRow, NodeRow, NodeState
from db.nodes import decommission_node, get_node, list_nodes, recommission_node, update_node_details
from service import schemas

log = logging.getLogger("pipesentry.api")


def node_views(session: Session, *, include_decommissioned: bool = False) -> list[schemas.Node]:
    """The nodes in service (or every node), ordered by id (three queries, whatever the fleet size)."""
    nodes = list_nodes(session, include_decommissioned=include_decommissioned)
    baselines = {
        b.node_id: b for b in session.scalars(select(BaselineRow).where(BaselineRow.active.is_(True)))
    }
    return [_node_view(n, baselines.get(n.node_id), d) for n, d in zip(nodes, _latest_detections(session, nodes), strict=True)]


def node_view(session: Session, node_id: str) -> schemas.Node:
    node = get_node(session, node_id)
    baseline = session.scalars(
        select(BaselineRow).where(BaselineRow.node_id == node_id, BaselineRow.active.is_(True))
    ).first()
    return _node_view(node, baseline, _latest_detections(session, [node])[0])


def site_summaries(session: Session) -> list[schemas.SiteSummary]:
    return [schemas.SiteSummary(site=s.site, gateways=s.gateways, nodes=s.nodes, flagged=s.flagged, offline=s.offline,
                                by_state=s.by_state, last_seen_at=s.last_seen_at)
            for s in fleet_queries.site_summaries(session)]


def fleet_page(session: Session, *, site: str | None, gateway_id: str | None, states: Sequence[NodeState],
               limit: int, cursor: str | None) -> schemas.FleetNodePage:
    """A page of the fleet's nodes in service (five queries per page, whatever the fleet size)."""
    nodes, next_cursor = fleet_queries.fleet_node_page(session, site=site, gateway_id=gateway_id, states=states,
                                                        limit=limit, cursor=cursor)
    ids = [n.node_id for n in nodes]
    baselines = {b.node_id: b for b in session.scalars(
        select(BaselineRow).where(BaselineRow.active.is_(True), BaselineRow.node_id.in_(ids)))} if ids else {}
    since = fleet_queries.state_since(session, nodes)
    items = [schemas.FleetNode(**_node_view(n, baselines.get(n.node_id), d).model_dump(), state_since=since.get(n.node_id))
             for n, d in zip(nodes, _latest_detections(session, nodes), strict=True)]
    return schemas.FleetNodePage(items=items, next_cursor=next_cursor)


def _latest_detections(session: Session, nodes: Sequence[NodeRow]) -> list[DetectionRow | None]:
    if not nodes:
        return []
    # The newest detection per node: ids grow with time within a node (one writer per node).
    newest = (
        select(func.max(DetectionRow.id))
        .where(DetectionRow.node_id.in_([n.node_id for n in nodes]))
        .group_by(DetectionRow.node_id)
        .scalar_subquery()
    )
    by_node = {d.node_id: d for d in session.scalars(select(DetectionRow).where(DetectionRow.id.in_(newest)))}
    return [by_node.get(n.node_id) for n in nodes]


def _node_view(node: NodeRow, baseline: BaselineRow | None, detection: DetectionRow | None) -> schemas.Node:
    return schemas.Node(
        node_id=node.node_id,
        details=schemas.NodeDetails(
            label=node.label,
            location=node.location,
            notes=node.notes,
            updated_at=node.details_updated_at,
            updated_by=node.details_updated_by,
        ),
        decommissioned=None
        if node.decommissioned_at is None
        else schemas.Decommissioned(
            at=node.decommissioned_at, by=node.decommissioned_by or "", reason=node.decommission_reason or ""
        ),
        port_url=node.port_url,
        firmware=node.firmware,
        protocol_version=node.protocol_version,
        n_channels=node.n_channels,
        fs_hz=node.fs_hz,
        geometry=None if node.geometry is None else schemas.Geometry.model_validate(node.geometry),
        health=schemas.Health(
            online=node.online, never_seen=node.never_seen, watched_since=node.watched_since,
            first_seen_at=node.first_seen_at, last_seen_at=node.last_seen_at,
            reported_node_id=node.reported_node_id, boot_id=node.boot_id, reboots=node.reboots or 0,
            last_reboot_at=node.last_reboot_at,
            applied_settings=None if node.applied_settings is None
            else schemas.AppliedSettings.model_validate(node.applied_settings),
            problems=[str(p) for p in node.link_problems or []],
        ),
        error_counters={str(k): int(v) for k, v in (node.error_counters or {}).items()},
        state=node.state,
        latest_di_peak=node.latest_di_peak,
        latest_threshold=node.latest_threshold,
        active_baseline=None if baseline is None else schemas.Baseline.model_validate(baseline),
        latest_detection=None if detection is None else schemas.Detection.model_validate(detection),
        site=node.site,
        gateway_id=node.gateway_id,
    )


def update_details(session: Session, node_id: str, update: schemas.NodeDetailsUpdate, *, who: str) -> schemas.Node:
    """Change the fields the request names (call in a write transaction)."""
    update_node_details(session, node_id, update.model_dump(exclude_unset=True), who=who)
    return node_view(session, node_id)


def decommission(session: Session, node_id: str, reason: str, *, who: str) -> schemas.Node:
    decommission_node(session, node_id, who=who, reason=reason)
    log.warning("node %s decommissioned by %s: %s", node_id, who, reason)
    return node_view(session, node_id)


def recommission(session: Session, node_id: str, *, who: str) -> schemas.Node:
    recommission_node(session, node_id)
    log.warning("node %s recommissioned by %s", node_id, who)
    return node_view(session, node_id)
