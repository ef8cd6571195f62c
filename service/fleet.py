"""The fleet as operators see it: each node's identity, health, state, baseline and latest verdict."""
from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db.models import BaselineRow, DetectionRow, NodeRow
from db.nodes import get_node
from service import schemas


def node_views(session: Session) -> list[schemas.Node]:
    """Every node, ordered by id (three queries, whatever the fleet size)."""
    nodes = session.scalars(select(NodeRow).order_by(NodeRow.node_id)).all()
    baselines = {
        b.node_id: b for b in session.scalars(select(BaselineRow).where(BaselineRow.active.is_(True)))
    }
    return [_node_view(n, baselines.get(n.node_id), d) for n, d in zip(nodes, _latest_detections(session, nodes))]


def node_view(session: Session, node_id: str) -> schemas.Node:
    node = get_node(session, node_id)
    baseline = session.scalars(
        select(BaselineRow).where(BaselineRow.node_id == node_id, BaselineRow.active.is_(True))
    ).first()
    return _node_view(node, baseline, _latest_detections(session, [node])[0])


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
        port_url=node.port_url,
        firmware=node.firmware,
        protocol_version=node.protocol_version,
        n_channels=node.n_channels,
        fs_hz=node.fs_hz,
        geometry=schemas.Geometry.model_validate(node.geometry),
        health=schemas.Health(online=node.online, first_seen_at=node.first_seen_at, last_seen_at=node.last_seen_at),
        error_counters={str(k): int(v) for k, v in (node.error_counters or {}).items()},
        state=node.state,
        latest_di_peak=node.latest_di_peak,
        latest_threshold=node.latest_threshold,
        active_baseline=None if baseline is None else schemas.Baseline.model_validate(baseline),
        latest_detection=None if detection is None else schemas.Detection.model_validate(detection),
    )
