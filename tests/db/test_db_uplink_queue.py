"""The uplink queue: written in the transaction of what it replicates, in order per node, fair across
nodes, and respected by retention until the centre has the traces."""
from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select

from db.cycles import store_cycle
from db.database import open_database
from db.models import MeasurementKind, MeasurementRow, NodeState, UplinkKind, UplinkRow, UplinkStatus
from db.nodes import upsert_node
from db.records import CycleRecord, DetectionInput
from db.retention import prune_traces
from db.uplink_queue import (
    QueuePolicy,
    answer_trace_request,
    mark_sent,
    next_batch,
    note_refusal,
    queue_stats,
    rotate,
    traces_go_up,
)
from tests.support.db_fixtures import T0, minutes, node_info
from tests.support.uplink_records import acquisition, commission_and_flag, queued


@pytest.fixture
def queueing_db(sqlite_url: str):
    db = open_database(sqlite_url)
    db.queue_uplink(QueuePolicy("everything"))
    yield db
    db.dispose()


def test_a_cycle_queues_its_node_measurement_detection_state_change_baseline_and_event_in_that_order(queueing_db):
    base_id, monitor_id = commission_and_flag(queueing_db)
    kinds = [(kind, ref) for kind, _node, ref, _traces in queued(queueing_db)]
    assert [k for k, _ in kinds] == ["node", "measurement", "state_change", "baseline",
                                     "measurement", "detection", "state_change", "alert_event"]
    assert kinds[1] == ("measurement", str(base_id)) and kinds[4] == ("measurement", str(monitor_id))
    assert {node for _k, node, _r, _t in queued(queueing_db)} == {"node-a"}


def test_a_cycle_that_fails_queues_nothing(queueing_db):
    with queueing_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
    with pytest.raises(RuntimeError, match="disk"):
        with queueing_db.write() as session:
            store_cycle(session, "node-a", CycleRecord(acquisition(1), MeasurementKind.BASELINE, {}))
            raise RuntimeError("disk full, say")
    assert [kind for kind, *_ in queued(queueing_db)] == ["node"]


def test_a_database_handle_that_does_not_queue_writes_no_queue(sqlite_db):
    commission_and_flag(sqlite_db)
    assert queued(sqlite_db) == []


def test_a_reconnecting_node_is_queued_again_only_once_its_pending_record_went_up(queueing_db):
    for _ in range(3):
        with queueing_db.write() as session:
            upsert_node(session, node_info(), seen_at=T0)
    assert [kind for kind, *_ in queued(queueing_db)] == ["node"]
    with queueing_db.write() as session:
        mark_sent(session, [row.id for row in next_batch(session, limit=10)])
        upsert_node(session, node_info(), seen_at=T0)
    assert [kind for kind, *_ in queued(queueing_db)] == ["node", "node"]


def test_a_node_that_never_answered_is_queued_at_its_first_answer_followed_by_the_events_stored_about_it_meanwhile(
    queueing_db,
):
    from alerts.config import AlertingSettings
    from alerts.outages import check_outages
    from db.nodes import register_configured_node
    from gateway.uplink.records import wire_records

    alerting = AlertingSettings(offline_after_s=60)
    with queueing_db.write() as session:
        register_configured_node(session, "node-q", port_url="tcp://127.0.0.1:9", now=T0)
        offline, = check_outages(session, alerting, now=T0 + minutes(2), watching_since=T0)
    assert queued(queueing_db) == []  # the centre would refuse an event about a node it does not know
    with queueing_db.write() as session:
        upsert_node(session, node_info("node-q"), seen_at=T0 + minutes(3))
        online, = check_outages(session, alerting, now=T0 + minutes(3), watching_since=T0)
    assert queued(queueing_db) == [("node", "node-q", "node-q", False), ("alert_event", "node-q", offline.id.hex, False),
                                   ("alert_event", "node-q", online.id.hex, False)]
    with queueing_db.session() as session:
        made, unreadable = wire_records(session, "gw-1", next_batch(session, limit=10))
    assert unreadable == {} and [w.record.kind for w in made] == ["node", "alert_event", "alert_event"]
    assert made[1].record.payload["never_seen"] is True and made[2].record.payload["first_seen"] is True


def test_a_node_record_of_a_node_that_never_answered_is_not_made(queueing_db):
    from db.nodes import register_configured_node
    from db.uplink_queue import enqueue
    from gateway.uplink.records import wire_records

    with queueing_db.write() as session:  # not queued by the gateway; a queue from elsewhere must not send it
        register_configured_node(session, "node-q", port_url="tcp://127.0.0.1:9", now=T0)
        row = enqueue(session, UplinkKind.NODE, "node-q", node_id="node-q")
        session.flush()
        made, unreadable = wire_records(session, "gw-1", [row])
    assert made == [] and unreadable == {row.id: "node node-q has never answered: nothing to replicate yet"}


def test_flagged_traces_sends_traces_only_of_flagged_measurements_and_baselines():
    policy = QueuePolicy("flagged_traces")
    calm = dict(kind=MeasurementKind.MONITOR, detection_state=NodeState.OK, peak_di=0.1, threshold=0.3,
                to_state=None, becomes_baseline=False)
    assert not traces_go_up(policy, **calm)
    assert traces_go_up(policy, **{**calm, "peak_di": 0.3})  # at the threshold is flagged
    assert traces_go_up(policy, **{**calm, "detection_state": NodeState.DAMAGE})
    assert traces_go_up(policy, **{**calm, "to_state": NodeState.SUSPECTED})
    assert traces_go_up(policy, **{**calm, "kind": MeasurementKind.BASELINE})
    assert traces_go_up(policy, **{**calm, "becomes_baseline": True})
    assert traces_go_up(QueuePolicy("everything"), **calm)


def test_retention_keeps_the_traces_a_record_still_has_to_carry_and_prunes_them_once_sent(queueing_db):
    with queueing_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        for seed in range(1, 4):
            store_cycle(session, "node-a", CycleRecord(
                acquisition(seed), MeasurementKind.MONITOR, {},
                detection=DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK)))
    later = T0 + timedelta(days=400)
    assert prune_traces(queueing_db.write, timedelta(days=365), 10, now=later) == 0
    with queueing_db.write() as session:
        first_two = [row.id for row in next_batch(session, limit=100)
                     if row.kind == UplinkKind.MEASUREMENT][:2]
        mark_sent(session, first_two)
    assert prune_traces(queueing_db.write, timedelta(days=365), 10, now=later) == 2
    with queueing_db.session() as session:
        kept = session.scalars(select(MeasurementRow.node_measurement_id)
                               .where(MeasurementRow.traces_pruned_at.is_(None))).all()
    assert kept == [3]


def test_retention_prunes_traces_that_no_record_is_to_carry(sqlite_url):
    db = open_database(sqlite_url)
    db.queue_uplink(QueuePolicy("flagged_traces"))
    with db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        store_cycle(session, "node-a", CycleRecord(
            acquisition(1), MeasurementKind.MONITOR, {},
            detection=DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK)))
        store_cycle(session, "node-a", CycleRecord(
            acquisition(2), MeasurementKind.MONITOR, {},
            detection=DetectionInput(peak_di=0.9, threshold=0.3, state=NodeState.OK)))
    assert [t for kind, _n, _r, t in queued(db) if kind == "measurement"] == [False, True]
    assert prune_traces(db.write, timedelta(days=365), 10, now=T0 + timedelta(days=400)) == 1  # the calm one
    db.dispose()


def test_a_batch_takes_each_nodes_oldest_records_in_order_sharing_the_batch_between_nodes(queueing_db):
    for index, node in enumerate(("node-a", "node-b", "node-c")):
        with queueing_db.write() as session:
            upsert_node(session, node_info(node), seen_at=T0)
            for seed in range(1, 6 if node == "node-a" else 2):  # node-a has a backlog, b and c one live record each
                store_cycle(session, node, CycleRecord(acquisition(10 * index + seed), MeasurementKind.MONITOR, {}))
    with queueing_db.session() as session:
        batch = next_batch(session, limit=6)
    by_node = {}
    for row in batch:
        by_node.setdefault(row.node_id, []).append(row.id)
    assert set(by_node) == {"node-a", "node-b", "node-c"}  # a backlog never fills the batch alone
    assert all(ids == sorted(ids) for ids in by_node.values())
    with queueing_db.session() as session:
        everything = session.scalars(select(UplinkRow.id).where(UplinkRow.node_id == "node-a")
                                     .order_by(UplinkRow.id)).all()
    assert by_node["node-a"] == list(everything[: len(by_node["node-a"])])  # a prefix of its queue


def test_when_a_batch_holds_fewer_records_than_there_are_nodes_the_nodes_take_turns(queueing_db):
    for node in ("node-a", "node-b", "node-c"):
        with queueing_db.write() as session:
            upsert_node(session, node_info(node), seen_at=T0)
    with queueing_db.session() as session:
        first = next_batch(session, limit=1)
        second = next_batch(session, limit=1, after_node=first[0].node_id)
        third = next_batch(session, limit=1, after_node=second[0].node_id)
        fourth = next_batch(session, limit=1, after_node=third[0].node_id)
    assert [b[0].node_id for b in (first, second, third, fourth)] == ["node-a", "node-b", "node-c", "node-a"]
    assert rotate(["a", "b", "c"], "b") == ["c", "a", "b"] and rotate(["a", "b"], "z") == ["a", "b"]


def test_a_refused_record_is_set_aside_after_the_limit_and_then_holds_nothing_up(queueing_db):
    with queueing_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
    with queueing_db.write() as session:
        (node_row,) = next_batch(session, limit=10)
        assert not note_refusal(session, node_row.id, "422 bad", give_up_after=2)
        assert note_refusal(session, node_row.id, "422 bad again", give_up_after=2)
    with queueing_db.session() as session:
        assert next_batch(session, limit=10) == []
        stats = queue_stats(session)
        row = session.get(UplinkRow, node_row.id)
    assert (stats.depth, stats.refused) == (0, 1)
    assert row.status == UplinkStatus.REFUSED and row.last_error == "422 bad again"


def test_the_queue_says_its_depth_and_how_long_its_oldest_unsent_record_has_waited(queueing_db):
    with queueing_db.write() as session:
        assert queue_stats(session).lag_s(T0) == 0.0
        upsert_node(session, node_info(), seen_at=T0)
        upsert_node(session, node_info("node-b"), seen_at=T0 + minutes(1))
    with queueing_db.session() as session:
        stats = queue_stats(session)
    assert stats.depth == 2 and stats.oldest_pending_at == T0
    assert stats.lag_s(T0 + minutes(5)) == 300.0


def test_a_database_that_predates_the_uplink_sends_the_nodes_earlier_baselines_first(sqlite_url):
    before = open_database(sqlite_url)
    base_id, monitor_id = commission_and_flag(before)  # stored without a queue
    before.dispose()
    db = open_database(sqlite_url)
    db.queue_uplink(QueuePolicy("flagged_traces"))
    with db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)  # the gateway connects
    assert [(kind, ref, traces) for kind, _n, ref, traces in queued(db)] == [
        ("node", "node-a", False), ("measurement", str(base_id), True), ("baseline", "1", False)]
    assert str(monitor_id) not in {ref for _k, _n, ref, _t in queued(db)}  # the rest of the history stays here
    db.dispose()


def test_a_trace_request_queues_the_measurement_again_with_its_traces_once_and_never_pruned_ones(sqlite_url):
    db = open_database(sqlite_url)
    db.queue_uplink(QueuePolicy("flagged_traces"))
    with db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        calm, older = (store_cycle(session, "node-a", CycleRecord(
            acquisition(seed), MeasurementKind.MONITOR, {},
            detection=DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK))).measurement_id for seed in (2, 1))
    with db.write() as session:
        mark_sent(session, [row.id for row in session.scalars(select(UplinkRow))])
    assert prune_traces(db.write, timedelta(minutes=90), 10, now=T0 + minutes(92)) == 1  # the older one only

    with db.write() as session:
        assert answer_trace_request(session, "gw-a", f"gw-a/measurement/{calm}") == "held"
        assert answer_trace_request(session, "gw-a", f"gw-a/measurement/{calm}") == "held"  # the answer was lost
        assert answer_trace_request(session, "gw-a", f"gw-a/measurement/{older}") == "pruned"
        assert answer_trace_request(session, "gw-a", "gw-a/measurement/99999") == "pruned"
        assert answer_trace_request(session, "gw-a", f"gw-b/measurement/{calm}") == "pruned"  # not this gateway's
    assert queued(db)[-1:] == [("measurement", "node-a", str(calm), True)]
    assert sum(1 for row in queued(db) if row[2] == str(calm) and row[0] == "measurement") == 2  # once more
    # Until the centre has them, retention keeps them.
    assert prune_traces(db.write, timedelta(0), 10, now=T0 + minutes(500)) == 0
    db.dispose()
