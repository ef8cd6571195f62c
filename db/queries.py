"""Read-side queries used by the API and the gateway: history, latest results, pages, and what a
node's next verdict depends on (calibration peaks, recent verdicts, recent sensor faults)."""
from __future__ import annotations

from collections.abc import Collection, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import func, select
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
    """The most recent verdict for a node, the last stored (None before its first monitor measurement).

    "Most recent" is insertion order, never a timestamp: a clock that stepped forward would make a
    future-dated verdict the latest for as long as the step was."""
    statement = select(DetectionRow).where(DetectionRow.node_id == node_id).order_by(DetectionRow.id.desc()).limit(1)
    return session.scalars(statement).first()


def latest_detections(session: Session, node_ids: Collection[str]) -> dict[str, DetectionRow]:
    """The last stored verdict of each of ``node_ids`` (nodes without one are absent), in one query."""
    if not node_ids:
        return {}
    rank = func.row_number().over(partition_by=DetectionRow.node_id, order_by=DetectionRow.id.desc()).label("rank")
    ranked = select(DetectionRow.id, rank).where(DetectionRow.node_id.in_(list(node_ids))).subquery()
    rows = session.scalars(
        select(DetectionRow).join(ranked, ranked.c.id == DetectionRow.id).where(ranked.c.rank == 1)
    ).all()
    return {row.node_id: row for row in rows}


def detection_for(session: Session, measurement_id: int) -> DetectionRow | None:
    """The verdict stored with a measurement, if any."""
    return session.scalars(select(DetectionRow).where(DetectionRow.measurement_id == measurement_id)).first()


def di_maps_for(session: Session, measurement_id: int) -> Sequence[DiMapRow]:
    """The DI maps of a measurement, in the order they were stored (pixels not loaded)."""
    return session.scalars(
        select(DiMapRow).where(DiMapRow.measurement_id == measurement_id).order_by(DiMapRow.id)
    ).all()


def baseline_count(session: Session, node_id: str) -> int:
    """How many of the node's measurements are stored as baselines (commissioning and library)."""
    statement = select(func.count()).where(
        MeasurementRow.node_id == node_id, MeasurementRow.kind == MeasurementKind.BASELINE
    )
    return int(session.scalar(statement) or 0)


def calibration_peaks(session: Session, node_id: str, *, after_measurement_id: int, limit: int) -> list[float]:
    """The first ``limit`` peak DIs without a threshold (calibration readings) of measurements stored after
    ``after_measurement_id`` (the active baseline's), oldest first.

    After, in insertion order: not "since the baseline's created_at", which a clock stepped back
    would never reach again (calibration frozen for as long as the step)."""
    rows = session.scalars(
        select(DetectionRow.peak_di)
        .where(
            DetectionRow.node_id == node_id,
            DetectionRow.measurement_id > after_measurement_id,
            DetectionRow.threshold.is_(None),
            DetectionRow.peak_di.is_not(None),
        )
        .order_by(DetectionRow.id)
        .limit(limit)
    ).all()
    return [float(p) for p in rows if p is not None]


def recent_verdicts(session: Session, node_id: str, *, limit: int) -> list[tuple[float, float]]:
    """(peak DI, threshold) of the node's last ``limit`` flagged readings (both set), newest first."""
    rows = session.execute(
        select(DetectionRow.peak_di, DetectionRow.threshold)
        .where(
            DetectionRow.node_id == node_id,
            DetectionRow.threshold.is_not(None),
            DetectionRow.peak_di.is_not(None),
        )
        .order_by(DetectionRow.id.desc())
        .limit(limit)
    ).all()
    return [(float(peak), float(threshold)) for peak, threshold in rows if peak is not None and threshold is not None]


def recent_sensor_faults(
    session: Session, node_id: str, *, limit: int, exclude_measurement_id: int | None = None
) -> list[list[Any] | None]:
    """``detections.sensor_faults`` of the node's last ``limit`` verdicts, newest first (None: none stored)."""
    statement = select(DetectionRow.sensor_faults).where(DetectionRow.node_id == node_id)
    if exclude_measurement_id is not None:
        statement = statement.where(DetectionRow.measurement_id != exclude_measurement_id)
    return list(session.scalars(statement.order_by(DetectionRow.id.desc()).limit(limit)).all())
