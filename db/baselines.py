"""Active baseline per node: exactly one at a time, every change kept as history.

A database that queues for an uplink queues every baseline record written or deactivated here
in the same transaction (``db.uplink_queue.enqueue_baselines``): the deactivated ones first, then
the new one, after its measurement."""
from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import BaselineError
from db.measurements import get_measurement
from db.models import BaselineRow, MeasurementKind, MeasurementRow
from db.nodes import get_node
from db.uplink_queue import enqueue_baselines


def active_baseline(session: Session, node_id: str) -> BaselineRow | None:
    """The node's active baseline record (its ``measurement_id`` names the measurement)."""
    return session.scalars(
        select(BaselineRow).where(BaselineRow.node_id == node_id, BaselineRow.active.is_(True))
    ).first()


def active_baseline_measurement(session: Session, node_id: str) -> MeasurementRow | None:
    """The measurement the node's DI maps are currently computed against."""
    baseline = active_baseline(session, node_id)
    return None if baseline is None else get_measurement(session, baseline.measurement_id)


def set_active_baseline(
    session: Session,
    node_id: str,
    measurement_id: int,
    *,
    created_by: str,
    reason: str,
    now: datetime | None = None,
) -> BaselineRow:
    """Make ``measurement_id`` the node's baseline; the previous one stays as history.

    Raises :class:`BaselineError` if the measurement belongs to another node or its traces
    were pruned (a baseline must be re-imageable). The partial unique index
    ``uq_baselines_one_active_per_node`` backs this up inside the database.
    """
    _baseline_candidate(session, node_id, measurement_id)
    now = now or utc_now()
    deactivated = list(session.scalars(
        select(BaselineRow).where(BaselineRow.node_id == node_id, BaselineRow.active.is_(True)).order_by(BaselineRow.id)
    ))
    # Deactivate first, as its own statement, so the unique index never sees two active rows.
    session.execute(
        update(BaselineRow)
        .where(BaselineRow.node_id == node_id, BaselineRow.active.is_(True))
        .values(active=False, deactivated_at=now)
        .execution_options(synchronize_session="fetch")
    )
    baseline = BaselineRow(
        node_id=node_id,
        measurement_id=measurement_id,
        created_by=created_by,
        created_at=now,
        reason=reason,
        active=True,
        deactivated_at=None,
    )
    session.add(baseline)
    session.flush()
    enqueue_baselines(session, node_id, [*deactivated, baseline], now=now)
    return baseline


def add_library_baseline(
    session: Session, node_id: str, measurement_id: int, *, created_by: str, reason: str, now: datetime | None = None,
) -> BaselineRow:
    """An inactive baseline record: the measurement joins the node's temperature library (its kind
    becomes ``baseline``) while the active baseline stays. Raises :class:`BaselineError` as
    :func:`set_active_baseline` does."""
    measurement = _baseline_candidate(session, node_id, measurement_id)
    measurement.kind = MeasurementKind.BASELINE
    now = now or utc_now()
    row = BaselineRow(node_id=node_id, measurement_id=measurement.id, created_by=created_by, created_at=now,
                      reason=reason, active=False, deactivated_at=None)
    session.add(row)
    session.flush()
    enqueue_baselines(session, node_id, [row], now=now)
    return row


def _baseline_candidate(session: Session, node_id: str, measurement_id: int) -> MeasurementRow:
    """The measurement that is to become one of the node's baselines; :class:`BaselineError` if it belongs
    to another node or its traces were pruned (a baseline must be re-imageable)."""
    get_node(session, node_id)
    measurement = get_measurement(session, measurement_id)
    if measurement.node_id != node_id:
        raise BaselineError(f"measurement {measurement_id} belongs to node {measurement.node_id!r}, not {node_id!r}")
    if measurement.traces_pruned_at is not None:
        raise BaselineError(f"measurement {measurement_id} has no traces any more (pruned); it cannot be a baseline")
    return measurement


def baseline_history(session: Session, node_id: str) -> Sequence[BaselineRow]:
    """Every baseline the node has had, newest first."""
    return session.scalars(
        select(BaselineRow)
        .where(BaselineRow.node_id == node_id)
        .order_by(BaselineRow.created_at.desc(), BaselineRow.id.desc())
    ).all()


def library_baseline_ids(session: Session, node_id: str, size: int) -> list[int]:
    """The node's baseline library for optimal baseline selection: the active baseline first, then
    its most recent other baseline measurements whose traces are kept, at most ``size`` in all."""
    active = active_baseline(session, node_id)
    others = session.scalars(
        select(MeasurementRow.id)
        .where(
            MeasurementRow.node_id == node_id,
            MeasurementRow.kind == MeasurementKind.BASELINE,
            MeasurementRow.traces_pruned_at.is_(None),
        )
        .order_by(MeasurementRow.id.desc())
        .limit(size)
    ).all()
    if active is None:
        return list(others[:size])
    return ([active.measurement_id] + [i for i in others if i != active.measurement_id])[:size]
