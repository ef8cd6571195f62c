"""Storing one gateway cycle: the measurement and everything decided about it, in one transaction."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy.orm import Session

from db.baselines import set_active_baseline
from db.measurements import add_event_once, store_measurement
from db.nodes import record_node_health
from db.records import CycleRecord, EventInput

# The outbox events a stored measurement causes, built once its id is known (event ids derive from it).
EventsFor = Callable[[int], Sequence[EventInput]]


@dataclass(frozen=True)
class StoredCycle:
    measurement_id: int
    events: tuple[EventInput, ...]  # the events added to the outbox (a fact already there is not added again)


def store_cycle(
    session: Session, node_id: str, record: CycleRecord, events_for: EventsFor | None = None,
    *, now: datetime | None = None,
) -> StoredCycle:
    """Store ``record`` and the events it causes; call inside ``Database.write()``. ``now``: the storing
    clock's time (the rows' created_at, the node's last_seen_at; default the wall clock).

    The measurement, its maps, verdict and state change, the baseline it may become, its
    outbox events and the node's health are committed together or (on any error) not at all.
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
        now=now,
    )
    if record.activate_baseline is not None:
        set_active_baseline(session, node_id, row.id, created_by="gateway", reason=record.activate_baseline)
    events = tuple(
        event for event in (events_for(row.id) if events_for else ()) if add_event_once(session, event, node_id=node_id)
    )
    record_node_health(session, node_id, online=True, error_counters=record.error_counters, seen_at=now)
    return StoredCycle(row.id, events)
