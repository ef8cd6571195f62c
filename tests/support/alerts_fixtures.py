"""Shared set-up of the alerting tests: a real SQLite outbox with nodes, events put in as the gateway would."""
from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from alerts.config import AlertingSettings
from alerts.delivery import SinkWorker, make_transport
from alerts.events import sensor_fault_cleared_event, sensor_fault_event, state_change_event
from db.database import Database, open_database
from db.measurements import add_event
from db.models import DeliveryRow, EventRow, NodeRow, NodeState
from db.nodes import upsert_node
from db.records import EventInput
from tests.support.db_fixtures import node_info

NODES = ("node-a", "node-b", "node-c")
T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
# The transitions one node goes through, oldest first (each a distinct, ordered event).
CYCLE = [("ok", "suspected"), ("suspected", "damage"), ("damage", "ok"), ("ok", "suspected")]


@pytest.fixture
def outbox_db(tmp_path: Path) -> Iterator[Database]:
    database = open_database(f"sqlite:///{tmp_path / 'alerts.db'}")
    with database.write() as session:
        for node_id in NODES:
            upsert_node(session, node_info(node_id), seen_at=T0)
    yield database
    database.dispose()


def fast_policy(**overrides) -> dict:
    """Delivery policy for tests: short timeouts and backoff, a few tries."""
    policy = {"timeout_s": 0.5, "max_attempts": 8, "backoff_base_s": 0.01, "backoff_cap_s": 0.05}
    policy.update(overrides)
    return policy


def alerting(*sinks: dict, **top) -> AlertingSettings:
    return AlertingSettings.model_validate({"api_base_url": "http://127.0.0.1:8000", "poll_interval_s": 0.05,
                                            **top, "sinks": list(sinks)})


def put_state_events(database: Database, settings: AlertingSettings, node_ids=NODES, cycle=CYCLE,
                     start_measurement_id: int = 1) -> list[EventInput]:
    """Each node goes through ``cycle`` (its stored state follows); one transaction per event, in creation order."""
    events = []
    measurement_id = start_measurement_id
    for step, (from_state, to_state) in enumerate(cycle):
        for node_id in node_ids:
            event = state_change_event(
                settings, node_id=node_id, from_state=from_state, to_state=to_state, measurement_id=measurement_id,
                peak_di=0.5, threshold=0.3, axial_mm=200.0, angle_deg=90.0,
                occurred_at=T0 + timedelta(minutes=step),
            )
            measurement_id += 1
            with database.write() as session:
                session.get(NodeRow, node_id).state = NodeState(to_state)
                if event is not None:
                    add_event(session, event, node_id=node_id)
            if event is not None:
                events.append(event)
    return events


def dead_receiver(rx_index: int = 5, kind: str = "no_signal") -> dict:
    """A receiver's entry in ``detections.sensor_faults`` (``imaging.health.SensorFault.as_dict()``)."""
    return {"rx_index": rx_index, "rx_angle_deg": rx_index * 22.5, "kind": kind, "amplitude_ratio": 0.03,
            "delay_s": 0.0}


def sensor_fault_pair(settings: AlertingSettings, node_id: str = "node-a", fault: dict | None = None, *,
                      measurement_id: int = 7) -> tuple[EventInput, EventInput]:
    """A receiver's sensor_fault (at ``measurement_id``) and its clearing two measurements later."""
    fault = fault or dead_receiver()
    raised = sensor_fault_event(settings, node_id=node_id, fault=fault, measurement_id=measurement_id, state="ok",
                                faulty_receivers=[fault["rx_index"]], consecutive=2, occurred_at=T0)
    cleared = sensor_fault_cleared_event(
        settings, node_id=node_id, raised_event_id=raised.id, raised_receiver=raised.payload["receiver"],
        raised_measurement_id=measurement_id, measurement_id=measurement_id + 2, state="ok", faulty_receivers=[],
        consecutive=2, occurred_at=T0 + timedelta(minutes=2))
    return raised, cleared


def put_events(database: Database, events: list[EventInput]) -> list[EventInput]:
    """Each event in its own transaction, in order (as the gateway adds them)."""
    for event in events:
        with database.write() as session:
            add_event(session, event, node_id=event.payload["node_id"])
    return events


def deliveries(database: Database, sink: str | None = None) -> list[tuple[DeliveryRow, EventRow]]:
    with database.session() as session:
        query = select(DeliveryRow, EventRow).join(EventRow, EventRow.id == DeliveryRow.event_id)
        if sink is not None:
            query = query.where(DeliveryRow.sink == sink)
        return list(session.execute(query.order_by(EventRow.created_at, DeliveryRow.id)).all())


def sink_worker(settings: AlertingSettings, name: str, database: Database, stop: threading.Event, **kw) -> SinkWorker:
    sink = settings.sink(name)
    return SinkWorker(settings, sink, make_transport(sink, settings, database), database, stop=stop, **kw)


@pytest.fixture
def stop() -> Iterator[threading.Event]:
    event = threading.Event()
    yield event
    event.set()
