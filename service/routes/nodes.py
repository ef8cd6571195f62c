"""Nodes: the fleet list, one node, its measurements, detections and baselines."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Query, status

from db.models import MeasurementKind, NodeState
from service import baselines, fleet, history, schemas
from service.deps import Admin, DatabaseDep, Operator, require_viewer
from service.problems import problem_responses
from service.routes.parameters import DEFAULT_LIMIT, BaselineId, Cursor, End, Limit, NodeId, Start

router = APIRouter(prefix="/nodes", tags=["nodes"], dependencies=[Depends(require_viewer)],
                   responses=problem_responses(401, 403, 503))


@router.get("", summary="The nodes in service: identity, health, state, latest DI peak and threshold, baseline")
def list_nodes(
    database: DatabaseDep,
    include_decommissioned: bool = Query(False, description="also the nodes taken out of service"),
) -> list[schemas.Node]:
    with database.session() as session:
        return fleet.node_views(session, include_decommissioned=include_decommissioned)


@router.get("/{node_id}", responses=problem_responses(404))
def get_node_detail(node_id: NodeId, database: DatabaseDep) -> schemas.Node:
    with database.session() as session:
        return fleet.node_view(session, node_id)


@router.patch("/{node_id}", responses=problem_responses(404, 413),
              summary="Set the node's label, location or notes (admin)")
def update_node_details(
    node_id: NodeId, body: schemas.NodeDetailsUpdate, caller: Admin, database: DatabaseDep
) -> schemas.Node:
    with database.write() as session:
        return fleet.update_details(session, node_id, body, who=caller.name)


@router.post("/{node_id}/decommission", responses=problem_responses(404, 409, 413),
             summary="Take the node out of service: not polled, no outage alerts, history kept (admin)")
def decommission_node(
    node_id: NodeId, body: schemas.NodeDecommission, caller: Admin, database: DatabaseDep
) -> schemas.Node:
    with database.write() as session:
        return fleet.decommission(session, node_id, body.reason, who=caller.name)


@router.post("/{node_id}/recommission", responses=problem_responses(404, 409),
             summary="Put a decommissioned node back in service (admin)")
def recommission_node(node_id: NodeId, caller: Admin, database: DatabaseDep) -> schemas.Node:
    with database.write() as session:
        return fleet.recommission(session, node_id, who=caller.name)


@router.get("/{node_id}/measurements", responses=problem_responses(400, 404),
            summary="A node's measurements in [start, end), newest first by default, cursor-paged")
def list_measurements(
    node_id: NodeId,
    database: DatabaseDep,
    start: Start = None,
    end: End = None,
    kind: MeasurementKind | None = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
    order: str = Query("desc", pattern="^(asc|desc)$", description="desc: newest first"),
) -> schemas.MeasurementPage:
    with database.session() as session:
        return history.measurement_list(session, node_id, start=start, end=end, kind=kind, limit=limit, cursor=cursor,
                                        newest_first=order == "desc")


@router.get("/{node_id}/detections", responses=problem_responses(400, 404),
            summary="A node's detections and defect estimates, latest first")
def list_node_detections(
    node_id: NodeId,
    database: DatabaseDep,
    state: NodeState | None = None,
    start: Start = None,
    end: End = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> schemas.DetectionPage:
    with database.session() as session:
        return history.detection_list(session, node_id=node_id, state=state, start=start, end=end, limit=limit,
                                      cursor=cursor)


@router.get("/{node_id}/detections/latest", responses=problem_responses(404),
            summary="The node's latest verdict (404 before its first monitor measurement)")
def get_latest_detection(node_id: NodeId, database: DatabaseDep) -> schemas.Detection:
    with database.session() as session:
        return history.latest_detection_of(session, node_id)


@router.get("/{node_id}/baselines", responses=problem_responses(404),
            summary="Every baseline the node has had, newest first (who, when, why)")
def list_baselines(node_id: NodeId, database: DatabaseDep) -> list[schemas.Baseline]:
    with database.session() as session:
        return baselines.history(session, node_id)


@router.post("/{node_id}/baselines", status_code=status.HTTP_201_CREATED,
             responses=problem_responses(404, 409, 413), summary="Make a measurement a baseline (operator)")
def create_baseline(
    node_id: NodeId, body: schemas.BaselineCreate, caller: Operator, database: DatabaseDep
) -> schemas.Baseline:
    with database.write() as session:
        return baselines.create(session, node_id, body, who=caller.name)


@router.post("/{node_id}/baselines/{baseline_id}/activate", responses=problem_responses(404, 409, 413),
             summary="Make an earlier baseline the active one again (operator)")
def activate_baseline(
    node_id: NodeId, baseline_id: BaselineId, body: schemas.BaselineActivate, caller: Operator, database: DatabaseDep
) -> schemas.Baseline:
    with database.write() as session:
        return baselines.activate(session, node_id, baseline_id, body.reason, who=caller.name)
