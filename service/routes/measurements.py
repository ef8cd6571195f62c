"""One measurement: metadata, raw traces (JSON, .npz, CSV) and its DI maps (JSON, PNG); at a central
site, a request to its gateway for raw traces it did not send (operator)."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response, status

from db.measurements import get_measurement
from db.models import MapSource
from db.trace_requests import TracesState, request_traces_of
from service import history, maps, schemas, traces
from service.deps import DatabaseDep, Operator, require_viewer
from service.problems import TRACES_PRUNED, ApiProblem, problem_responses
from service.routes.parameters import MeasurementId

router = APIRouter(prefix="/measurements", tags=["measurements"], dependencies=[Depends(require_viewer)],
                   responses=problem_responses(401, 403, 404, 503))

PRUNED = problem_responses(410)


def _binary(media_type: str, description: str) -> dict:
    return {200: {"description": description, "content": {media_type: {"schema": {"type": "string",
                                                                                   "format": "binary"}}}}}


@router.get("/{measurement_id}")
def get_measurement_detail(measurement_id: MeasurementId, database: DatabaseDep) -> schemas.Measurement:
    with database.session() as session:
        return history.measurement_detail(session, measurement_id)


@router.get("/{measurement_id}/traces.npz", response_class=Response,
            responses={**_binary("application/octet-stream", "the .npz interchange file (docs/formats.md)"), **PRUNED})
def get_traces_npz(measurement_id: MeasurementId, database: DatabaseDep) -> Response:
    with database.session() as session:
        return Response(
            traces.traces_npz(session, measurement_id),
            media_type="application/octet-stream",
            headers={"Content-Disposition": f'attachment; filename="measurement-{measurement_id}.npz"'},
        )


@router.get("/{measurement_id}/traces.csv", response_class=Response,
            responses={**_binary("text/csv", "the CSV form (docs/formats.md)"), **PRUNED})
def get_traces_csv(measurement_id: MeasurementId, database: DatabaseDep) -> Response:
    with database.session() as session:
        return Response(
            traces.traces_csv(session, measurement_id),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="measurement-{measurement_id}.csv"'},
        )


@router.get("/{measurement_id}/traces", responses=PRUNED,
            summary="Raw traces as JSON, in volts (codes x volts_per_code) or raw ADC codes")
def get_traces(
    measurement_id: MeasurementId,
    database: DatabaseDep,
    units: Annotated[schemas.TraceUnits, Query()] = schemas.TraceUnits.VOLTS,
) -> schemas.Traces:
    with database.session() as session:
        return traces.traces_json(session, measurement_id, units)


@router.get("/{measurement_id}/di-maps", summary="The measurement's DI maps (node's and gateway's), no pixels")
def list_di_maps(measurement_id: MeasurementId, database: DatabaseDep) -> list[schemas.DiMapSummary]:
    with database.session() as session:
        return history.measurement_detail(session, measurement_id).di_maps


@router.get("/{measurement_id}/di-maps/{source}.png", response_class=Response,
            responses=_binary("image/png", "heatmap: axial distance x angle, the estimated defect marked"))
def get_di_map_png(measurement_id: MeasurementId, source: MapSource, request: Request,
                   database: DatabaseDep) -> Response:
    with database.session() as session:
        renderer: maps.HeatmapRenderer = request.app.state.heatmaps
        return Response(renderer.png(session, measurement_id, source), media_type="image/png",
                        headers={"Cache-Control": "private, max-age=3600"})


@router.get("/{measurement_id}/di-maps/{source}", summary="A DI map's grid, pixels and estimated defect")
def get_di_map(measurement_id: MeasurementId, source: MapSource, database: DatabaseDep) -> schemas.DiMap:
    with database.session() as session:
        return maps.map_json(session, measurement_id, source)


@router.post(
    "/{measurement_id}/traces/request", status_code=status.HTTP_202_ACCEPTED,
    summary="Ask the measurement's gateway for the raw traces it did not send (operator, central site)",
    responses={200: {"description": "the traces are here already: nothing to ask",
                     "model": schemas.TracesState}, **PRUNED},
)
def request_traces(measurement_id: MeasurementId, caller: Operator, database: DatabaseDep,
                   response: Response) -> schemas.TracesState:
    """202: asked (or asked already and not yet in): the gateway polls for it, answers and sends them;
    ``GET /measurements/{id}`` shows ``traces.status`` move to held, then received (or pruned, or refused
    with the ``refusal``: asked again from there, the request starts over)."""
    with database.write() as session:
        outcome, state = request_traces_of(session, get_measurement(session, measurement_id), who=caller.name)
    if outcome == "gone":
        raise ApiProblem(TRACES_PRUNED, _gone(measurement_id, state))
    if outcome == "here":
        response.status_code = status.HTTP_200_OK
    return schemas.TracesState.model_validate(state)


def _gone(measurement_id: int, state: TracesState) -> str:
    if state.status == "pruned":
        when = state.answered_at.isoformat() if state.answered_at is not None else "?"
        return (f"gateway {state.gateway_id!r} answered at {when} that it no longer holds the raw traces of "
                f"measurement {measurement_id} (retention removed them)")
    return f"the raw traces of measurement {measurement_id} were removed by retention here; no gateway has them to send"
