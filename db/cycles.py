"""Storing one gateway cycle: the measurement and everything decided about it, in one transaction."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from db.baselines import set_active_baseline
from db.measurements import add_event_once, store_measurement
from db.models import DetectionRow, MeasurementRow, StateChangeRow, UplinkKind
from db.nodes import record_node_health
from db.records import CycleRecord, EventInput
from db.uplink_queue import QueuePolicy, enqueue, queue_policy, traces_go_up

# The outbox events a stored measurement causes, built once its id is known (event ids derive from it).
EventsFor = Callable[[int], Sequence[EventInput]]


@dataclass(frozen=True)
class StoredCycle:
    measurement_id: int
    events: tuple[EventInput, ...]  # the events added to the outbox (a fact already there is not added again)


def store_cycle(session: Session, node_id: str, record: CycleRecord, events_for: EventsFor | None = None) -> StoredCycle:
    """Store ``record`` and the events it causes; call inside ``Database.write()``.

    The measurement, its maps, verdict and state change, the baseline it may become, its
    outbox events, their uplink records (when the session queues for an uplink) and the node's
    health are committed together or (on any error) not at all.
    """
    acquisition = record.acquisition
    row = store_measurement(
        session,
        node_id,
        kind=record.kind,
        acquired_at=acquisition.acquired_at,
        node_measurement_id=acquisition.node_measurement_id,
        codes=acquisition.codes,
        volts_per_code=acquisition.volts_per_code,
        fs_hz=acquisition.fs_hz,
        t0_s=acquisition.t0_s,
        averaging=acquisition.averaging,
        excitation_hz=acquisition.excitation_hz,
        cycles=acquisition.cycles,
        temperature_c=acquisition.temperature_c,
        velocity_m_s=acquisition.velocity_m_s,
        wall_mm=acquisition.wall_mm,
        boot_id=acquisition.boot_id,
        di_maps=record.di_maps,
        detection=record.detection,
        state_change=record.state_change,
    )
    policy = queue_policy(session)
    if policy is not None:  # before the events: a node's records go up in the order they happened
        _queue_cycle(session, policy, node_id, row, record)
    if record.activate_baseline is not None:  # after its measurement: it queues its baseline records itself
        set_active_baseline(session, node_id, row.id, created_by="gateway", reason=record.activate_baseline)
    events = tuple(
        event for event in (events_for(row.id) if events_for else ()) if add_event_once(session, event, node_id=node_id)
    )
    record_node_health(session, node_id, online=True, error_counters=record.error_counters)
    return StoredCycle(row.id, events)


def _queue_cycle(
    session: Session, policy: QueuePolicy, node_id: str, row: MeasurementRow, record: CycleRecord,
) -> None:
    """The cycle's uplink records: the measurement (with its maps), then its detection and state change
    (the baseline it becomes, and the one it replaces, follow: ``set_active_baseline``)."""
    # (The node's own record is queued when the gateway connects to it: upsert_node.)
    detection, state_change = record.detection, record.state_change
    with_traces = traces_go_up(
        policy, kind=record.kind, detection_state=detection.state if detection else None,
        peak_di=detection.peak_di if detection else None, threshold=detection.threshold if detection else None,
        to_state=state_change.to_state if state_change else None,
        becomes_baseline=record.activate_baseline is not None,
    )
    enqueue(session, UplinkKind.MEASUREMENT, row.id, node_id=node_id, measurement_id=row.id, with_traces=with_traces)
    if detection is not None:
        detection_id = session.scalar(select(DetectionRow.id).where(DetectionRow.measurement_id == row.id))
        enqueue(session, UplinkKind.DETECTION, detection_id or row.id, node_id=node_id, measurement_id=row.id)
    if state_change is not None:
        change_id = session.scalar(select(StateChangeRow.id).where(StateChangeRow.measurement_id == row.id))
        enqueue(session, UplinkKind.STATE_CHANGE, change_id or row.id, node_id=node_id, measurement_id=row.id)

