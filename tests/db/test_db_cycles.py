"""Storing one gateway cycle in one transaction, and the queries a node's next verdict depends on."""
from __future__ import annotations

import uuid

import pytest
from sqlalchemy import func, select

from db.baselines import active_baseline
from db.cycles import store_cycle
from db.errors import StateConflict
from db.models import DeliveryRow, EventRow, MeasurementKind, MeasurementRow, NodeState, Severity
from db.nodes import get_node, upsert_node
from db.queries import baseline_count, calibration_peaks, recent_sensor_faults, recent_verdicts
from db.records import (
    AcquisitionInput,
    CycleRecord,
    DetectionInput,
    DiMapInput,
    EventInput,
    MapSource,
    StateChangeInput,
)
from tests.support.db_fixtures import GRID, T0, minutes, node_info, sample_codes, sample_pixels, store_sample


def acquisition(seed: int = 1) -> AcquisitionInput:
    return AcquisitionInput(acquired_at=T0 + minutes(seed), node_measurement_id=seed, codes=sample_codes(seed),
                            volts_per_code=1.0 / 32768, fs_hz=2.0e6, t0_s=1.0e-5, averaging=16, excitation_hz=85e3,
                            cycles=5, temperature_c=21.5)


def alert_for(measurement_id: int) -> list[EventInput]:
    eid = uuid.uuid5(uuid.NAMESPACE_URL, f"test/{measurement_id}")
    return [EventInput("damage_raised", Severity.CRITICAL, {"measurement_id": measurement_id}, ("hook",), eid)]


def counts(db) -> dict[str, int]:
    with db.session() as session:
        return {name: session.scalar(select(func.count()).select_from(model))
                for name, model in (("measurements", MeasurementRow), ("events", EventRow))}


def test_a_commissioning_cycle_stores_its_record_as_the_active_baseline_with_the_node_health(any_db):
    with any_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        record = CycleRecord(acquisition(), MeasurementKind.BASELINE, {"gateway_cycles": 1},
                             state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.CALIBRATING),
                             activate_baseline="commissioning: first measurement")
        stored = store_cycle(session, "node-a", record)
    with any_db.session() as session:
        baseline = active_baseline(session, "node-a")
        assert baseline.measurement_id == stored.measurement_id and baseline.created_by == "gateway"
        node = get_node(session, "node-a")
        assert node.state == NodeState.CALIBRATING and node.error_counters == {"gateway_cycles": 1} and node.online
        assert baseline_count(session, "node-a") == 1 and stored.events == ()


def test_a_monitor_cycle_stores_its_maps_verdict_and_the_events_named_by_its_measurement_id(any_db):
    with any_db.write() as session:
        base = store_sample(session, kind=MeasurementKind.BASELINE)
        record = CycleRecord(
            acquisition(2), MeasurementKind.MONITOR, {},
            di_maps=[DiMapInput(MapSource.GATEWAY, "multipath", GRID, sample_pixels(2), base.id)],
            detection=DetectionInput(peak_di=0.42, threshold=0.3, state=NodeState.SUSPECTED),
            state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.SUSPECTED),
        )
        stored = store_cycle(session, "node-a", record, alert_for)
    with any_db.session() as session:
        (event,) = session.scalars(select(EventRow)).all()
        assert event.payload == {"measurement_id": stored.measurement_id} and [e.id for e in stored.events] == [event.id]
        assert session.scalar(select(func.count()).select_from(DeliveryRow)) == 1
        assert get_node(session, "node-a").latest_di_peak == 0.42


def test_an_event_already_in_the_outbox_is_not_added_again(sqlite_db):
    with sqlite_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        first = store_cycle(session, "node-a", CycleRecord(acquisition(1), MeasurementKind.BASELINE, {}),
                            lambda _mid: alert_for(1))
        again = store_cycle(session, "node-a", CycleRecord(acquisition(2), MeasurementKind.MONITOR, {}),
                            lambda _mid: alert_for(1))
    assert len(first.events) == 1 and again.events == ()
    assert counts(sqlite_db) == {"measurements": 2, "events": 1}


def test_a_cycle_whose_state_change_conflicts_stores_nothing_at_all(any_db):
    with any_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
    record = CycleRecord(acquisition(), MeasurementKind.MONITOR, {},
                         detection=DetectionInput(peak_di=0.42, threshold=0.3, state=NodeState.DAMAGE),
                         state_change=StateChangeInput(NodeState.OK, NodeState.DAMAGE))  # the node is commissioning
    with pytest.raises(StateConflict), any_db.write() as session:
        store_cycle(session, "node-a", record, alert_for)
    assert counts(any_db) == {"measurements": 0, "events": 0}


def test_calibration_peaks_are_the_first_unthresholded_peaks_stored_after_the_baseline(any_db):
    with any_db.write() as session:
        baseline = store_sample(session, seed=99, acquired_at=T0, kind=MeasurementKind.BASELINE).id
        for seed, (peak, threshold) in enumerate([(0.5, None), (None, None), (0.1, None), (0.2, 0.3), (0.3, None)]):
            # the clock stepped back an hour after the baseline: stored after it all the same
            store_sample(session, seed=seed, acquired_at=T0 - minutes(60 - seed),
                         detection=DetectionInput(peak_di=peak, threshold=threshold, state=NodeState.CALIBRATING))
    with any_db.session() as session:
        assert calibration_peaks(session, "node-a", after_measurement_id=baseline, limit=2) == [0.5, 0.1]
        assert calibration_peaks(session, "node-a", after_measurement_id=baseline, limit=10) == [0.5, 0.1, 0.3]
        assert calibration_peaks(session, "node-a", after_measurement_id=baseline + 2, limit=10) == [0.1, 0.3]
        assert recent_verdicts(session, "node-a", limit=5) == [(0.2, 0.3)]


def test_recent_verdicts_and_sensor_faults_are_newest_first(any_db):
    with any_db.write() as session:
        for seed in range(4):
            store_sample(session, seed=seed, detection=DetectionInput(
                peak_di=0.1 * seed, threshold=0.25, state=NodeState.OK, sensor_faults=[{"rx_index": seed}]))
    with any_db.session() as session:
        assert recent_verdicts(session, "node-a", limit=2) == [(pytest.approx(0.3), 0.25), (0.2, 0.25)]
        assert recent_sensor_faults(session, "node-a", limit=2) == [[{"rx_index": 3}], [{"rx_index": 2}]]
        last_id = session.scalar(select(func.max(MeasurementRow.id)))
        assert recent_sensor_faults(session, "node-a", limit=1, exclude_measurement_id=last_id) == [[{"rx_index": 2}]]
