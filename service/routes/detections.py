"""Fleet-wide detections and defect estimates, latest first."""
from __future__ import annotations

from fastapi import APIRouter, Depends

from db.models import NodeState
from service import history, schemas
from service.deps import DatabaseDep, require_viewer
from service.problems import problem_responses
from service.routes.parameters import DEFAULT_LIMIT, Cursor, End, GatewayFilter, Limit, NodeIdFilter, SiteFilter, Start

router = APIRouter(prefix="/detections", tags=["detections"], dependencies=[Depends(require_viewer)],
                   responses=problem_responses(401, 403, 503))


@router.get("", responses=problem_responses(400, 404))
def list_detections(
    database: DatabaseDep,
    node_id: NodeIdFilter = None,
    state: NodeState | None = None,
    start: Start = None,
    end: End = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
    site: SiteFilter = None,
    gateway_id: GatewayFilter = None,
) -> schemas.DetectionPage:
    with database.session() as session:
        return history.detection_list(session, node_id=node_id, state=state, start=start, end=end, limit=limit,
                                      cursor=cursor, site=site, gateway_id=gateway_id)
