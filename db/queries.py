"""Read-side queries used by the API and the gateway: history, latest results, pages."""
from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.models import DetectionRow, DiMapRow, MeasurementKind, MeasurementRow, StateChangeRow
from db.pagination import Page, keyset_page

DEFAULT_PAGE_SIZE = 100


def measurements_page(
    session: Session,
    node_id: str,
    *,
    start: datetime | None = None,
    end: datetime | None = None,
    kind: MeasurementKind | None = None,
    limit: int = DEFAULT_PAGE_SIZE,
    cursor: str | None = None,
    newest_first: bool = True,
) -> Page[MeasurementRow]:
    """A node's measurements acquired in [start, end), one page at a time (blobs not loaded)."""
    statement = select(MeasurementRow).where(MeasurementRow.node_id == node_id)
    if start is not None:
        statement = statement.where(MeasurementRow.acquired_at >= start)
    if end is not None:
        statement = statement.where(MeasurementRow.acquired_at < end)
    if kind is not None:
        statement = statement.where(MeasurementRow.kind == kind)
    return keyset_page(
        session,
        statement,
        time_column=MeasurementRow.acquired_at,
        id_column=MeasurementRow.id,
        limit=limit,
        cursor=cursor,
        newest_first=newest_first,
    )


def state_history(
    session: Session,
    node_id: str,
    *,
    limit: int = DEFAULT_PAGE_SIZE,
    cursor: str | None = None,
    newest_first: bool = True,
) -> Page[StateChangeRow]:
    """A node's state transitions, one page at a time."""
    statement = select(StateChangeRow).where(StateChangeRow.node_id == node_id)
    return keyset_page(
        session,
        statement,
        time_column=StateChangeRow.at,
        id_column=StateChangeRow.id,
        limit=limit,
        cursor=cursor,
        newest_first=newest_first,
    )


def latest_detection(session: Session, node_id: str) -> DetectionRow | None:
    """The most recent verdict for a node (None before its first monitor measurement)."""
    statement = (
        select(DetectionRow)
        .where(DetectionRow.node_id == node_id)
        .order_by(DetectionRow.created_at.desc(), DetectionRow.id.desc())
        .limit(1)
    )
    return session.scalars(statement).first()


def detection_for(session: Session, measurement_id: int) -> DetectionRow | None:
    """The verdict stored with a measurement, if any."""
    return session.scalars(select(DetectionRow).where(DetectionRow.measurement_id == measurement_id)).first()


def di_maps_for(session: Session, measurement_id: int) -> Sequence[DiMapRow]:
    """The DI maps of a measurement, in the order they were stored (pixels not loaded)."""
    return session.scalars(
        select(DiMapRow).where(DiMapRow.measurement_id == measurement_id).order_by(DiMapRow.id)
    ).all()
