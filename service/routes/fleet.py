"""The fleet across sites (a central site's view): a summary per site, then nodes paged with filters."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query

from db.models import NodeState
from service import fleet, schemas
from service.deps import DatabaseDep, require_viewer
from service.problems import problem_responses
from service.routes.parameters import DEFAULT_LIMIT, Cursor, GatewayFilter, Limit, SiteFilter

router = APIRouter(prefix="/fleet", tags=["fleet"], dependencies=[Depends(require_viewer)],
                   responses=problem_responses(401, 403, 503))


@router.get("/sites", summary="One summary per site: gateways, nodes in service, flagged, offline, by state")
def list_sites(database: DatabaseDep) -> list[schemas.SiteSummary]:
    with database.session() as session:
        return fleet.site_summaries(session)


@router.get("/nodes", responses=problem_responses(400),
            summary="The nodes in service across sites, by node id, paged; which are damaged, where, since when")
def list_fleet_nodes(
    database: DatabaseDep,
    site: SiteFilter = None,
    gateway_id: GatewayFilter = None,
    state: Annotated[list[NodeState] | None, Query(description="only nodes in these states (repeatable)")] = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> schemas.FleetNodePage:
    with database.session() as session:
        return fleet.fleet_page(session, site=site, gateway_id=gateway_id, states=state or (), limit=limit,
                                cursor=cursor)
