"""Records stored the way the gateway stores them, and the uplink queue as a list: shared by the
uplink-queue tests of tests/db."""
from __future__ import annotations

import uuid

from sqlalchemy import select

from db.cycles import store_cycle
from db.database import Database
from db.models import MeasurementKind, NodeState, Severity, UplinkRow
from db.nodes import upsert_node
from db.records import AcquisitionInput, CycleRecord, DetectionInput, EventInput, StateChangeInput
from tests.support.db_fixtures import T0, minutes, node_info, sample_codes


def acquisition(seed: int) -> AcquisitionInput:
    return AcquisitionInput(acquired_at=T0 + minutes(seed), node_measurement_id=seed, codes=sample_codes(seed),
                            volts_per_code=1.0 / 32768, fs_hz=2.0e6, t0_s=1.0e-5, averaging=16, excitation_hz=85e3,
                            cycles=5, temperature_c=21.5)


def queued(db: Database) -> list[tuple[str, str | None, str, bool]]:
    with db.session() as session:
        rows = session.scalars(select(UplinkRow).order_by(UplinkRow.id)).all()
        return [(row.kind.value, row.node_id, row.ref, row.with_traces) for row in rows]


def commission_and_flag(db: Database, node_id: str = "node-a", *, first_seed: int = 1) -> tuple[int, int]:
    """A baseline cycle, then a monitor cycle that flags the node suspected with an alert event."""
    with db.write() as session:
        upsert_node(session, node_info(node_id), seen_at=T0)
        base = store_cycle(session, node_id, CycleRecord(
            acquisition(first_seed), MeasurementKind.BASELINE, {},
            state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.OK),
            activate_baseline="commissioning"))
    with db.write() as session:
        event = EventInput("damage_suspected", Severity.WARNING, {"x": 1}, ("hook",), uuid.uuid4())
        monitor = store_cycle(session, node_id, CycleRecord(
            acquisition(first_seed + 1), MeasurementKind.MONITOR, {},
            detection=DetectionInput(peak_di=0.5, threshold=0.3, state=NodeState.SUSPECTED),
            state_change=StateChangeInput(NodeState.OK, NodeState.SUSPECTED)), lambda _mid: [event])
    return base.measurement_id, monitor.measurement_id
