"""Operators' baseline decisions: create one from a measurement, (re)activate one; history is kept."""
from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.baselines import add_library_baseline, baseline_history, set_active_baseline
from db.errors import NotFound
from db.models import BaselineRow
from db.nodes import get_node
from service import schemas


def history(session: Session, node_id: str) -> list[schemas.Baseline]:
    get_node(session, node_id)
    return [schemas.Baseline.model_validate(b) for b in baseline_history(session, node_id)]


def create(session: Session, node_id: str, request: schemas.BaselineCreate, *, who: str) -> schemas.Baseline:
    """A baseline record for a measurement of this node, made active unless ``activate`` is false.

    Inactive, the measurement joins the node's temperature library (its kind becomes
    ``baseline``: the gateway compares records with it too, retention keeps it) while the
    active baseline and the threshold stay as they are: how an operator teaches a node a
    temperature it has not seen in its first weeks. Call in a write transaction. Raises
    ``BaselineError`` for another node's or a pruned measurement, ``NotFound`` for an unknown
    node or measurement.
    """
    if request.activate:
        row = set_active_baseline(session, node_id, request.measurement_id, created_by=who, reason=request.reason)
        return schemas.Baseline.model_validate(row)
    row = add_library_baseline(session, node_id, request.measurement_id, created_by=who, reason=request.reason)
    return schemas.Baseline.model_validate(row)


def activate(session: Session, node_id: str, baseline_id: int, reason: str, *, who: str) -> schemas.Baseline:
    """Make an earlier baseline's measurement the active one again (a new history record)."""
    earlier = session.scalars(
        select(BaselineRow).where(BaselineRow.id == baseline_id, BaselineRow.node_id == node_id)
    ).first()
    if earlier is None:
        get_node(session, node_id)
        raise NotFound(f"node {node_id!r} has no baseline {baseline_id}")
    row = set_active_baseline(session, node_id, earlier.measurement_id, created_by=who, reason=reason)
    return schemas.Baseline.model_validate(row)
