"""Alerts: list (viewer), acknowledge and resolve (operator)."""
from __future__ import annotations

import uuid

from fastapi import APIRouter, Depends

from db.models import Severity
from service import alerts, schemas
from service.deps import DatabaseDep, Operator, require_viewer
from service.problems import problem_responses
from service.routes.parameters import DEFAULT_LIMIT, Cursor, Limit, NodeIdFilter

router = APIRouter(prefix="/alerts", tags=["alerts"], dependencies=[Depends(require_viewer)],
                   responses=problem_responses(401, 403, 503))


@router.get("", responses=problem_responses(400), summary="Alerts newest first, filtered by status/node/severity")
def list_alerts(
    database: DatabaseDep,
    status: schemas.AlertStatus | None = None,
    node_id: NodeIdFilter = None,
    severity: Severity | None = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> schemas.AlertPage:
    with database.session() as session:
        return alerts.alert_list(session, status=status, node_id=node_id, severity=severity, limit=limit, cursor=cursor)


@router.get("/{alert_id}", responses=problem_responses(404))
def get_alert(alert_id: uuid.UUID, database: DatabaseDep) -> schemas.Alert:
    with database.session() as session:
        return alerts.get_alert(session, alert_id)


@router.post("/{alert_id}/acknowledge", responses=problem_responses(404), summary="Acknowledge (operator)")
def acknowledge_alert(alert_id: uuid.UUID, caller: Operator, database: DatabaseDep) -> schemas.Alert:
    with database.write() as session:
        return alerts.acknowledge(session, alert_id, who=caller.name)


@router.post("/{alert_id}/resolve", responses=problem_responses(404), summary="Resolve (operator)")
def resolve_alert(alert_id: uuid.UUID, caller: Operator, database: DatabaseDep) -> schemas.Alert:
    with database.write() as session:
        return alerts.resolve(session, alert_id, who=caller.name)
