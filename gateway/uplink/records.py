"""The queue's records as the wire contract has them: database rows -> ``uplink.contract`` records.

A record is read when it is sent, not when it was queued: a node's record carries the node's
latest view (the contract applies it as an update), an alert event its latest handling. Raw
traces travel as stored (compressed, with their SHA-256) when the queue says so and they are
still held; otherwise the measurement is described without them.
"""
from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session, undefer

from db.models import (
    BaselineRow,
    DeliveryRow,
    DetectionRow,
    DiMapRow,
    EventRow,
    MeasurementRow,
    NodeRow,
    StateChangeRow,
    UplinkKind,
    UplinkRow,
)
from uplink.contract import (
    AlertEventRecord,
    BaselineRecord,
    Blob,
    DetectionRecord,
    DiMapRecord,
    MeasurementRecord,
    MeasurementSettings,
    NodeRecord,
    Record,
    RecordKind,
    StateChangeRecord,
    record_uid,
)

T = TypeVar("T")


class RecordUnreadable(ValueError):
    """The queued row cannot be made into a record (its fact is gone, or a stored blob is damaged)."""


@dataclass(frozen=True)
class Wire:
    """One queue row and the record it is sent as."""

    row_id: int
    node_id: str | None
    record: Record


def uid_of(gateway_id: str, row: UplinkRow) -> str:
    return record_uid(gateway_id, _kind(row.kind), row.ref)


def wire_records(session: Session, gateway_id: str, rows: Sequence[UplinkRow]) -> tuple[list[Wire], dict[int, str]]:
    """The records of ``rows`` in their order, and the rows that could not be made (id -> why)."""
    made: list[Wire] = []
    unreadable: dict[int, str] = {}
    for row in rows:
        try:
            made.append(Wire(row.id, row.node_id, _record(session, gateway_id, row)))
        except RecordUnreadable as exc:
            unreadable[row.id] = str(exc)
        except ValidationError as exc:  # a stored value the contract refuses (a damaged blob, a too long text)
            unreadable[row.id] = f"not a valid {row.kind.value} record: {exc.errors()[0]['msg']}"
    return made, unreadable


def _kind(kind: UplinkKind) -> RecordKind:
    return kind.value  # UplinkKind's values are exactly RecordKind's


def _record(session: Session, gw: str, row: UplinkRow) -> Record:
    uid = uid_of(gw, row)
    kind = row.kind
    if kind == UplinkKind.NODE:
        return _node(_get(session, NodeRow, row.ref), uid)
    if kind == UplinkKind.MEASUREMENT:
        return _measurement(session, gw, int(row.ref), uid, with_traces=row.with_traces)
    if kind == UplinkKind.DETECTION:
        detection = _get(session, DetectionRow, int(row.ref))
        return DetectionRecord(
            uid=uid, node_id=detection.node_id, measurement_uid=record_uid(gw, "measurement", detection.measurement_id),
            peak_di=detection.peak_di, threshold=detection.threshold, axial_mm=detection.axial_mm,
            angle_deg=detection.angle_deg, state=detection.state.value, confidence=detection.confidence,
            method=detection.method, defects=detection.defects, sensor_faults=detection.sensor_faults,
            baseline_measurement_uid=_measurement_uid(gw, detection.baseline_measurement_id),
            stretch=detection.stretch, abstain_reason=detection.abstain_reason, created_at=detection.created_at,
        )
    if kind == UplinkKind.STATE_CHANGE:
        change = _get(session, StateChangeRow, int(row.ref))
        return StateChangeRecord(
            uid=uid, node_id=change.node_id, measurement_uid=_measurement_uid(gw, change.measurement_id),
            from_state=change.from_state.value, to_state=change.to_state.value, at=change.at,
        )
    if kind == UplinkKind.BASELINE:
        baseline = _get(session, BaselineRow, int(row.ref))
        return BaselineRecord(
            uid=uid, node_id=baseline.node_id, measurement_uid=record_uid(gw, "measurement", baseline.measurement_id),
            created_by=baseline.created_by, created_at=baseline.created_at, reason=baseline.reason,
            active=baseline.active, deactivated_at=baseline.deactivated_at,
        )
    if kind == UplinkKind.ALERT_EVENT:
        event = _get(session, EventRow, uuid.UUID(row.ref))
        sent_here = session.scalar(select(DeliveryRow.id).where(DeliveryRow.event_id == event.id).limit(1))
        return AlertEventRecord(
            uid=uid, event_id=event.id, node_id=event.node_id, event_kind=event.kind, severity=event.severity.value,
            payload=dict(event.payload), created_at=event.created_at,
            deliver_centrally=sent_here is None,  # no sink of this gateway sends it: the centre's may
        )
    raise RecordUnreadable(f"unknown record kind {kind!r}")


def _get(session: Session, model: type[T], key: object) -> T:
    found = session.get(model, key)
    if found is None:
        raise RecordUnreadable(f"{model.__name__} {key} is no longer in the database")
    return found


def _measurement_uid(gw: str, measurement_id: int | None) -> str | None:
    return None if measurement_id is None else record_uid(gw, "measurement", measurement_id)


def _node(node: NodeRow, uid: str) -> NodeRecord:
    # Queued at an INFO (upsert_node) and at an admin's change once it answered; a node registered from the configuration that never answered
    # has nothing the contract could carry (no channels, no geometry), so it is not sent.
    if (node.firmware is None or node.protocol_version is None or node.n_channels is None or node.fs_hz is None
            or node.geometry is None or node.first_seen_at is None or node.last_seen_at is None):
        raise RecordUnreadable(f"node {node.node_id} has never answered: nothing to replicate yet")
    return NodeRecord(
        uid=uid, node_id=node.node_id, firmware=node.firmware, protocol_version=node.protocol_version,
        n_channels=node.n_channels, fs_hz=node.fs_hz, geometry=dict(node.geometry), first_seen_at=node.first_seen_at,
        last_seen_at=node.last_seen_at, online=node.online, state=node.state.value,
        latest_di_peak=node.latest_di_peak, latest_threshold=node.latest_threshold, label=node.label,
        location=node.location, decommissioned_at=node.decommissioned_at, decommissioned_by=node.decommissioned_by,
        decommission_reason=node.decommission_reason, revision=node.revision,
    )


def _measurement(session: Session, gw: str, measurement_id: int, uid: str, *, with_traces: bool) -> MeasurementRecord:
    query = select(MeasurementRow).where(MeasurementRow.id == measurement_id)
    if with_traces:
        query = query.options(undefer(MeasurementRow.traces_blob))
    m = session.scalars(query).first()
    if m is None:
        raise RecordUnreadable(f"measurement {measurement_id} is no longer in the database")
    stored = m.traces_blob if with_traces and m.traces_pruned_at is None else None
    maps = session.scalars(
        select(DiMapRow).where(DiMapRow.measurement_id == measurement_id).options(undefer(DiMapRow.pixels_blob))
        .order_by(DiMapRow.id)
    ).all()
    return MeasurementRecord(
        uid=uid, node_id=m.node_id, measurement_kind=m.kind.value, acquired_at=m.acquired_at,
        node_measurement_id=m.node_measurement_id, boot_id=m.boot_id,
        settings=MeasurementSettings(
            temperature_c=m.temperature_c, averaging=m.averaging, fs_hz=m.fs_hz, t0_s=m.t0_s,
            n_channels=m.n_channels, n_samples=m.n_samples, volts_per_code=m.volts_per_code,
            excitation_hz=m.excitation_hz, cycles=m.cycles,
        ),
        velocity_m_s=m.velocity_m_s, wall_mm=m.wall_mm,
        traces=Blob.of(stored, dtype="<i2", sha256=m.traces_sha256, nbytes=m.traces_nbytes),
        di_maps=[_di_map(gw, di_map) for di_map in maps],
    )


def _di_map(gw: str, di_map: DiMapRow) -> DiMapRecord:
    return DiMapRecord(
        source=di_map.source.value, method=di_map.method, grid=dict(di_map.grid),
        baseline_measurement_uid=_measurement_uid(gw, di_map.baseline_measurement_id),
        pixels=Blob.of(di_map.pixels_blob, dtype="<f4", sha256=di_map.pixels_sha256, nbytes=len(di_map.pixels_blob)),
        peak_di=di_map.peak_di, created_at=di_map.created_at,
    )
