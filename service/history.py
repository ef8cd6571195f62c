"""A node's history: measurements and detections, filtered by time and paged by keyset cursors."""
from __future__ import annotations

from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.errors import NotFound
from db.measurements import get_measurement
from db.models import DetectionRow, MeasurementKind, MeasurementRow, NodeRow, NodeState
from db.nodes import get_node
from db.pagination import keyset_page
from db.queries import detection_for, di_maps_for, latest_detection, measurements_page
from db.trace_requests import traces_state
from service import schemas


def measurement_summary(row: MeasurementRow) -> schemas.MeasurementSummary:
    return schemas.MeasurementSummary(
        id=row.id,
        node_id=row.node_id,
        kind=row.kind,
        acquired_at=row.acquired_at,
        node_measurement_id=row.node_measurement_id,
        temperature_c=row.temperature_c,
        n_channels=row.n_channels,
        n_samples=row.n_samples,
        traces_available=row.traces_pruned_at is None,
    )


def measurement_list(
    session: Session,
    node_id: str,
    *,
    start: datetime | None,
    end: datetime | None,
    kind: MeasurementKind | None,
    limit: int,
    cursor: str | None,
    newest_first: bool,
) -> schemas.MeasurementPage:
    get_node(session, node_id)  # 404 for an unknown node rather than an empty page
    page = measurements_page(
        session, node_id, start=start, end=end, kind=kind, limit=limit, cursor=cursor, newest_first=newest_first
    )
    return schemas.MeasurementPage(items=[measurement_summary(r) for r in page.items], next_cursor=page.next_cursor)


def measurement_detail(session: Session, measurement_id: int) -> schemas.Measurement:
    row = get_measurement(session, measurement_id)
    detection = detection_for(session, measurement_id)
    return schemas.Measurement(
        **measurement_summary(row).model_dump(),
        averaging=row.averaging,
        fs_hz=row.fs_hz,
        t0_s=row.t0_s,
        volts_per_code=row.volts_per_code,
        excitation_hz=row.excitation_hz,
        cycles=row.cycles,
        traces_pruned_at=row.traces_pruned_at,
        stored_at=row.stored_at,
        di_maps=[schemas.DiMapSummary.model_validate(m) for m in di_maps_for(session, measurement_id)],
        detection=None if detection is None else schemas.Detection.model_validate(detection),
        traces=schemas.TracesState.model_validate(traces_state(session, row)),
    )


def detection_list(
    session: Session,
    *,
    node_id: str | None,
    state: NodeState | None,
    start: datetime | None,
    end: datetime | None,
    limit: int,
    cursor: str | None,
    site: str | None = None,
    gateway_id: str | None = None,
) -> schemas.DetectionPage:
    """Detections, latest first: one node's (``node_id``) or the whole fleet's (of one site or gateway)."""
    statement = select(DetectionRow)
    if site is not None or gateway_id is not None:
        nodes = select(NodeRow.node_id)
        if site is not None:
            nodes = nodes.where(NodeRow.site == site)
        if gateway_id is not None:
            nodes = nodes.where(NodeRow.gateway_id == gateway_id)
        statement = statement.where(DetectionRow.node_id.in_(nodes))
    if node_id is not None:
        get_node(session, node_id)
        statement = statement.where(DetectionRow.node_id == node_id)
    if state is not None:
        statement = statement.where(DetectionRow.state == state)
    if start is not None:
        statement = statement.where(DetectionRow.created_at >= start)
    if end is not None:
        statement = statement.where(DetectionRow.created_at < end)
    page = keyset_page(
        session,
        statement,
        time_column=DetectionRow.created_at,
        id_column=DetectionRow.id,
        limit=limit,
        cursor=cursor,
        newest_first=True,
    )
    return schemas.DetectionPage(
        items=[schemas.Detection.model_validate(d) for d in page.items], next_cursor=page.next_cursor
    )


def latest_detection_of(session: Session, node_id: str) -> schemas.Detection:
    """The node's latest verdict; ``NotFound`` for an unknown node or one without a monitor measurement yet."""
    get_node(session, node_id)
    row = latest_detection(session, node_id)
    if row is None:
        raise NotFound(f"node {node_id!r} has no detection yet")
    return schemas.Detection.model_validate(row)
