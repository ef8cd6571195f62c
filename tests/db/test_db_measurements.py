"""Specification of storing measurements with their results, and reading them back."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from sqlalchemy import event, func, select, text, update
from sqlalchemy.exc import IntegrityError

from db.errors import CorruptBlob, InvalidCursor, NotFound, StateConflict
from db.measurements import get_measurement, load_pixels, load_traces, load_traces_volts, store_measurement
from db.models import (
    DeliveryRow,
    DeliveryStatus,
    DetectionRow,
    DiMapRow,
    EventRow,
    MeasurementKind,
    MeasurementRow,
    NodeRow,
    NodeState,
    Severity,
    StateChangeRow,
)
from db.nodes import get_node, record_node_health, upsert_node
from db.queries import detection_for, di_maps_for, latest_detection, measurements_page, state_history
from db.records import DetectionInput, DiMapInput, EventInput, MapSource, StateChangeInput
from tests.support.db_fixtures import ALARM, GRID, T0, minutes, node_info, sample_codes, sample_pixels, store_sample

TO_DAMAGE = StateChangeInput(NodeState.COMMISSIONING, NodeState.DAMAGE)


def _count(session, model) -> int:
    return session.scalar(select(func.count()).select_from(model))


def test_traces_and_metadata_round_trip(any_db):
    with any_db.write() as session:
        stored = store_sample(session, seed=11, acquired_at=T0)
        measurement_id = stored.id
    with any_db.session() as session:
        row = get_measurement(session, measurement_id)
        np.testing.assert_array_equal(load_traces(row), sample_codes(11))
        assert row.acquired_at == T0
        assert (row.n_channels, row.n_samples, row.kind) == (8, 2048, MeasurementKind.MONITOR)
        assert row.traces_nbytes == len(row.traces_blob) < sample_codes(11).nbytes
        volts = load_traces_volts(row)
        assert volts.dtype == np.float32
        np.testing.assert_allclose(volts, sample_codes(11) / 32768, rtol=1e-6)


def test_measurement_with_map_detection_state_change_and_events_is_stored_whole(any_db):
    event = EventInput("damage_detected", Severity.CRITICAL, {"peak_di": 0.42}, sinks=("webhook", "mqtt"))
    with any_db.write() as session:
        baseline = store_sample(session, kind=MeasurementKind.BASELINE, seed=1)
        monitor = store_measurement(
            session,
            "node-a",
            kind=MeasurementKind.MONITOR,
            acquired_at=T0 + minutes(10),
            node_measurement_id=2,
            codes=sample_codes(2),
            volts_per_code=1 / 32768,
            fs_hz=2e6,
            t0_s=0.0,
            averaging=16,
            excitation_hz=85e3,
            cycles=5,
            di_maps=[
                DiMapInput(MapSource.NODE, "node-das", GRID, sample_pixels(5), None),
                DiMapInput(MapSource.GATEWAY, "delay-and-sum", GRID, sample_pixels(6), baseline.id),
            ],
            detection=ALARM,
            state_change=TO_DAMAGE,
            events=[event],
        )
        monitor_id = monitor.id
    with any_db.session() as session:
        maps = di_maps_for(session, monitor_id)
        assert [m.source for m in maps] == [MapSource.NODE, MapSource.GATEWAY]
        assert maps[1].baseline_measurement_id == baseline.id
        np.testing.assert_array_equal(load_pixels(maps[1]), sample_pixels(6))
        assert maps[1].peak_di == pytest.approx(float(sample_pixels(6).max()))
        assert detection_for(session, monitor_id).state == NodeState.DAMAGE
        node = get_node(session, "node-a")
        assert (node.state, node.latest_di_peak, node.latest_threshold) == (NodeState.DAMAGE, 0.42, 0.3)
        stored_event = session.get(EventRow, event.id)
        assert stored_event.payload == {"peak_di": 0.42}
        deliveries = session.scalars(select(DeliveryRow).order_by(DeliveryRow.sink)).all()
        assert [(d.sink, d.status, d.attempts) for d in deliveries] == [
            ("mqtt", DeliveryStatus.PENDING, 0),
            ("webhook", DeliveryStatus.PENDING, 0),
        ]


def test_a_failure_part_way_stores_nothing_of_the_measurement(any_db):
    with any_db.write() as session:
        upsert_node(session, node_info("node-a"), seen_at=T0)
    bad_map = DiMapInput(MapSource.GATEWAY, "delay-and-sum", GRID, sample_pixels(1), baseline_measurement_id=999_999)
    with pytest.raises(IntegrityError):
        with any_db.write() as session:
            store_sample(session, detection=ALARM, state_change=TO_DAMAGE)
            store_measurement(
                session,
                "node-a",
                kind=MeasurementKind.MONITOR,
                acquired_at=T0,
                node_measurement_id=1,
                codes=sample_codes(1),
                volts_per_code=1.0,
                fs_hz=2e6,
                t0_s=0.0,
                averaging=1,
                excitation_hz=85e3,
                cycles=5,
                di_maps=[bad_map],  # the baseline does not exist: FK violation at flush
            )
    with any_db.session() as session:
        for model in (MeasurementRow, DiMapRow, DetectionRow, StateChangeRow, EventRow):
            assert _count(session, model) == 0, model.__tablename__
        assert get_node(session, "node-a").state == NodeState.COMMISSIONING


def test_state_change_must_start_from_the_current_state(any_db):
    with any_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
    with pytest.raises(StateConflict, match="commissioning"):
        with any_db.write() as session:
            store_sample(session, state_change=StateChangeInput(NodeState.OK, NodeState.DAMAGE))
    with any_db.session() as session:
        assert _count(session, MeasurementRow) == 0


def test_unknown_node_is_not_found(any_db):
    with pytest.raises(NotFound, match="ghost"):
        with any_db.write() as session:
            store_measurement(
                session, "ghost", kind=MeasurementKind.MONITOR, acquired_at=T0, node_measurement_id=1,
                codes=sample_codes(1), volts_per_code=1.0, fs_hz=2e6, t0_s=0.0, averaging=1,
                excitation_hz=85e3, cycles=5,
            )  # fmt: skip


def test_codes_must_be_int16_two_dimensional(any_db):
    with pytest.raises(ValueError, match="int16"):
        with any_db.write() as session:
            upsert_node(session, node_info(), seen_at=T0)
            store_measurement(
                session, "node-a", kind=MeasurementKind.MONITOR, acquired_at=T0, node_measurement_id=1,
                codes=sample_codes(1).astype(np.int32), volts_per_code=1.0, fs_hz=2e6, t0_s=0.0,
                averaging=1, excitation_hz=85e3, cycles=5,
            )  # fmt: skip


def test_damaged_traces_blob_is_reported_on_read(any_db):
    with any_db.write() as session:
        measurement_id = store_sample(session, seed=3).id
    with any_db.write() as session:
        blob = bytearray(get_measurement(session, measurement_id).traces_blob)
        blob[len(blob) // 2] ^= 0x10
        session.execute(update(MeasurementRow).where(MeasurementRow.id == measurement_id).values(traces_blob=bytes(blob)))
    with any_db.session() as session:
        with pytest.raises(CorruptBlob, match="checksum"):
            load_traces(get_measurement(session, measurement_id))


def test_damaged_pixels_blob_is_reported_on_read(any_db):
    with any_db.write() as session:
        measurement_id = store_sample(session, seed=3, with_map=True).id
        session.execute(update(DiMapRow).values(pixels_sha256="0" * 64))
    with any_db.session() as session:
        with pytest.raises(CorruptBlob):
            load_pixels(di_maps_for(session, measurement_id)[0])


def test_pages_walk_a_time_range_newest_first_without_gaps_or_repeats(any_db):
    with any_db.write() as session:
        ids = [store_sample(session, acquired_at=T0 + minutes(i // 2), seed=i).id for i in range(25)]
        store_sample(session, "node-b", acquired_at=T0 + minutes(3), seed=99)
    start, end = T0 + minutes(2), T0 + minutes(11)  # minutes 2..10 -> measurements 4..21
    seen, cursor = [], None
    with any_db.session() as session:
        for _ in range(10):  # bounded: 18 rows / 4 per page = 5 pages
            page = measurements_page(session, "node-a", start=start, end=end, limit=4, cursor=cursor)
            seen += [row.id for row in page.items]
            cursor = page.next_cursor
            if cursor is None:
                break
    assert seen == sorted(ids[4:22], reverse=True)


def test_pages_oldest_first_and_by_kind(any_db):
    with any_db.write() as session:
        kinds = [MeasurementKind.BASELINE if i % 3 == 0 else MeasurementKind.MONITOR for i in range(9)]
        ids = [store_sample(session, acquired_at=T0 + minutes(i), seed=i, kind=k).id for i, k in enumerate(kinds)]
    with any_db.session() as session:
        first = measurements_page(session, "node-a", kind=MeasurementKind.BASELINE, limit=2, newest_first=False)
        second = measurements_page(
            session, "node-a", kind=MeasurementKind.BASELINE, limit=2, newest_first=False, cursor=first.next_cursor
        )
    assert [r.id for r in first.items] == [ids[0], ids[3]]
    assert [r.id for r in second.items] == [ids[6]] and second.next_cursor is None


@pytest.mark.parametrize("cursor", ["garbage!", "eyJ2IjoyfQ", "", "eyJ2IjoxLCJ0Ijoibm9wZSIsImlkIjoxfQ"])
def test_malformed_cursor_is_a_typed_error(sqlite_db, cursor):
    with sqlite_db.session() as session:
        with pytest.raises(InvalidCursor):
            measurements_page(session, "node-a", cursor=cursor)


def test_latest_detection_and_state_history(any_db):
    with any_db.write() as session:
        assert latest_detection(session, "node-a") is None
        store_sample(session, acquired_at=T0, seed=1, detection=ALARM, state_change=TO_DAMAGE)
        calm = DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK)
        last = store_sample(
            session, acquired_at=T0 + minutes(5), seed=2, detection=calm,
            state_change=StateChangeInput(NodeState.DAMAGE, NodeState.OK),
        )  # fmt: skip
        last_id = last.id
    with any_db.session() as session:
        assert latest_detection(session, "node-a").measurement_id == last_id
        history = state_history(session, "node-a")
        assert [(c.from_state, c.to_state) for c in history.items] == [
            (NodeState.DAMAGE, NodeState.OK),
            (NodeState.COMMISSIONING, NodeState.DAMAGE),
        ]
        assert history.items[0].measurement_id == last_id


def test_node_refresh_keeps_state_and_health_is_recorded(any_db):
    with any_db.write() as session:
        store_sample(session, detection=ALARM, state_change=TO_DAMAGE)
        record_node_health(session, "node-a", online=False, error_counters={"crc": 3, "timeouts": 1})
    with any_db.write() as session:
        upsert_node(session, replace(node_info("node-a"), firmware="1.5.0"), seen_at=T0 + minutes(1))
    with any_db.session() as session:
        node = session.get(NodeRow, "node-a")
        assert (node.firmware, node.state, node.online) == ("1.5.0", NodeState.DAMAGE, True)
        assert node.error_counters == {"crc": 3, "timeouts": 1}
        assert node.geometry["rx_angles_deg"][1] == 45.0
        assert node.last_seen_at == T0 + minutes(1)


def test_listing_measurements_does_not_load_blobs(sqlite_db):
    with sqlite_db.write() as session:
        store_sample(session)
    statements: list[str] = []

    @event.listens_for(sqlite_db.engine, "before_cursor_execute")
    def _record(conn, cursor, statement, parameters, context, executemany):
        statements.append(statement)

    with sqlite_db.session() as session:
        measurements_page(session, "node-a")
    selects = [s for s in statements if s.lstrip().upper().startswith("SELECT")]
    assert selects and not any("traces_blob" in s for s in selects)


def test_check_constraint_forbids_a_missing_blob_that_was_not_pruned(any_db):
    with any_db.write() as session:
        measurement_id = store_sample(session).id
    with pytest.raises(IntegrityError):
        with any_db.write() as session:
            session.execute(text("UPDATE measurements SET traces_blob = NULL WHERE id = :id"), {"id": measurement_id})
