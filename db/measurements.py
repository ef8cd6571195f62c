"""Storing a measurement with everything derived from it, and reading its arrays back."""
from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

import numpy as np
from sqlalchemy.orm import Session

from db import blobs
from db.clock import utc_now
from db.errors import CorruptBlob, NotFound, StateConflict, TracesPruned
from db.models import (
    DeliveryRow,
    DeliveryStatus,
    DetectionRow,
    DiMapRow,
    EventRow,
    MeasurementKind,
    MeasurementRow,
    NodeRow,
    StateChangeRow,
    UplinkKind,
)
from db.nodes import get_node
from db.records import DetectionInput, DiMapInput, EventInput, StateChangeInput
from db.uplink_queue import enqueue, queue_policy


def store_measurement(
    session: Session,
    node_id: str,
    *,
    kind: MeasurementKind,
    acquired_at: datetime,
    node_measurement_id: int,
    codes: np.ndarray,
    volts_per_code: float,
    fs_hz: float,
    t0_s: float,
    averaging: int,
    excitation_hz: float,
    cycles: int,
    temperature_c: float | None = None,
    velocity_m_s: float | None = None,
    wall_mm: float | None = None,
    boot_id: int | None = None,
    di_maps: Sequence[DiMapInput] = (),
    detection: DetectionInput | None = None,
    state_change: StateChangeInput | None = None,
    events: Sequence[EventInput] = (),
    now: datetime | None = None,
) -> MeasurementRow:
    """Add one measurement (raw ADC codes, int16 [n_channels, n_samples]) and its results.

    ``velocity_m_s`` and ``wall_mm``: what the record was imaged with (None: not known).

    Call inside ``Database.write()``: the measurement, its DI maps, detection, state change,
    events and the node's new state are flushed together and become visible in one commit,
    or (on any error) not at all. Inputs are checked before anything is written.
    """
    if not session.in_transaction():
        raise RuntimeError("store_measurement needs an open write transaction (use Database.write())")
    codes = np.asarray(codes)
    if codes.ndim != 2 or codes.dtype != np.int16:
        raise ValueError(f"codes must be int16 [n_channels, n_samples], got {codes.dtype} {codes.shape}")
    node = get_node(session, node_id)
    if state_change is not None and state_change.from_state != node.state:
        raise StateConflict(
            f"node {node_id!r} is {node.state.value}, the state change starts from {state_change.from_state.value}"
        )
    now = now or utc_now()
    encoded = blobs.encode_array(codes, blobs.TRACE_DTYPE)
    measurement = MeasurementRow(
        node_id=node_id,
        kind=kind,
        acquired_at=acquired_at,
        node_measurement_id=node_measurement_id,
        temperature_c=temperature_c,
        averaging=averaging,
        fs_hz=fs_hz,
        t0_s=t0_s,
        n_channels=encoded.shape[0],
        n_samples=encoded.shape[1],
        volts_per_code=volts_per_code,
        excitation_hz=excitation_hz,
        cycles=cycles,
        velocity_m_s=velocity_m_s,
        wall_mm=wall_mm,
        boot_id=boot_id,
        traces_blob=encoded.data,
        traces_codec=encoded.codec,
        traces_dtype=encoded.dtype,
        traces_sha256=encoded.sha256,
        traces_nbytes=len(encoded.data),
        traces_pruned_at=None,
        stored_at=now,
    )
    session.add(measurement)
    session.flush()  # assigns measurement.id
    for di_map in di_maps:
        session.add(_di_map_row(measurement.id, di_map, now))
    if detection is not None:
        session.add(
            DetectionRow(
                measurement_id=measurement.id,
                node_id=node_id,
                peak_di=detection.peak_di,
                threshold=detection.threshold,
                axial_mm=detection.axial_mm,
                angle_deg=detection.angle_deg,
                state=detection.state,
                confidence=detection.confidence,
                method=detection.method,
                defects=detection.defects,
                sensor_faults=detection.sensor_faults,
                baseline_measurement_id=detection.baseline_measurement_id,
                stretch=detection.stretch,
                abstain_reason=detection.abstain_reason,
                created_at=now,
            )
        )
        node.latest_di_peak = detection.peak_di
        node.latest_threshold = detection.threshold
    if state_change is not None:
        session.add(
            StateChangeRow(
                node_id=node_id,
                measurement_id=measurement.id,
                from_state=state_change.from_state,
                to_state=state_change.to_state,
                at=now,
            )
        )
        node.state = state_change.to_state
    for event in events:
        add_event(session, event, node_id=node_id, now=now)
    session.flush()
    return measurement


def _di_map_row(measurement_id: int, di_map: DiMapInput, now: datetime) -> DiMapRow:
    encoded = blobs.encode_array(di_map.pixels, blobs.PIXEL_DTYPE)
    return DiMapRow(
        measurement_id=measurement_id,
        source=di_map.source,
        method=di_map.method,
        grid=di_map.grid.model_dump(mode="json"),
        baseline_measurement_id=di_map.baseline_measurement_id,
        pixels_blob=encoded.data,
        pixels_codec=encoded.codec,
        pixels_dtype=encoded.dtype,
        pixels_sha256=encoded.sha256,
        peak_di=di_map.peak_di,
        created_at=now,
    )


def add_event(session: Session, event: EventInput, *, node_id: str | None, now: datetime | None = None) -> EventRow:
    """Put an alert in the outbox with one pending delivery per sink (same transaction), and in
    the uplink queue when the session queues for one — an event about a node that never answered
    is queued with the node's first record instead (``enqueue_node``): the centre accepts an
    event only about a node it knows."""
    now = now or utc_now()
    row = EventRow(
        id=event.id,
        node_id=node_id,
        kind=event.kind,
        severity=event.severity,
        payload=dict(event.payload),
        created_at=now,
    )
    # Through the relationship, so the unit of work inserts the event before its deliveries.
    row.deliveries = [
        DeliveryRow(
            sink=sink,
            status=DeliveryStatus.PENDING,
            attempts=0,
            next_attempt_at=now,
            last_error=None,
        )
        for sink in event.sinks
    ]
    session.add(row)
    if queue_policy(session) is not None:
        about = None if node_id is None else session.get(NodeRow, node_id)
        if about is None or not about.never_seen:
            enqueue(session, UplinkKind.ALERT_EVENT, event.id.hex, node_id=node_id, now=now)
    return row


def add_event_once(session: Session, event: EventInput, *, node_id: str | None, now: datetime | None = None) -> bool:
    """Add ``event`` to the outbox unless an event with its (stable) id is already there."""
    if session.get(EventRow, event.id) is not None:
        return False
    add_event(session, event, node_id=node_id, now=now)
    session.flush()
    return True


def get_measurement(session: Session, measurement_id: int) -> MeasurementRow:
    """The measurement with this id; raises :class:`NotFound`."""
    row = session.get(MeasurementRow, measurement_id)
    if row is None:
        raise NotFound(f"no measurement {measurement_id}")
    return row


def load_traces(row: MeasurementRow) -> np.ndarray:
    """The raw ADC codes, int16 [n_channels, n_samples], checksum verified.

    ``row`` must be attached to an open session (the blob column is loaded on demand).
    Raises :class:`TracesPruned` after retention, :class:`CorruptBlob` on a bad blob.
    """
    if row.traces_pruned_at is not None:
        raise TracesPruned(f"traces of measurement {row.id} were pruned at {row.traces_pruned_at.isoformat()}")
    data = row.traces_blob
    if data is None:
        raise CorruptBlob(f"measurement {row.id} has no traces blob but was never pruned")
    return blobs.decode_array(
        data,
        dtype=row.traces_dtype,
        shape=(row.n_channels, row.n_samples),
        codec=row.traces_codec,
        sha256=row.traces_sha256,
    )


def load_traces_volts(row: MeasurementRow) -> np.ndarray:
    """The traces in volts, float32 [n_channels, n_samples] (codes x volts_per_code)."""
    return (load_traces(row).astype(np.float32) * np.float32(row.volts_per_code)).astype(np.float32)


def load_pixels(row: DiMapRow) -> np.ndarray:
    """DI map pixels, float32 [axial_count, angle_count], checksum verified."""
    grid = row.grid
    try:
        shape = (int(grid["axial_count"]), int(grid["angle_count"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CorruptBlob(f"DI map {row.id} has an unreadable grid: {error}") from error
    return blobs.decode_array(
        row.pixels_blob,
        dtype=row.pixels_dtype,
        shape=shape,
        codec=row.pixels_codec,
        sha256=row.pixels_sha256,
    )
