"""The uplink sender against a real HTTP server on 127.0.0.1 that answers as the centre does when it
stores, is busy, is gone, or refuses: what is marked sent, what waits, how long the sender waits."""
from __future__ import annotations

import random
import socket
import threading
import uuid

import pytest
from sqlalchemy import select

from db.cycles import store_cycle
from db.database import Database, open_database
from db.models import MeasurementKind, MeasurementRow, NodeState, Severity, UplinkRow, UplinkStatus
from db.nodes import upsert_node
from db.records import AcquisitionInput, CycleRecord, DetectionInput, EventInput, StateChangeInput
from db.uplink_queue import QueuePolicy, queue_stats
from gateway.config import UplinkSettings
from gateway.uplink.sender import UplinkSender
from tests.support.db_fixtures import T0, minutes, node_info, sample_codes
from tests.support.uplink_centre import Reply, ScriptedCentre, bad_record
from uplink.contract import INGEST_PATH, MeasurementRecord, record_uid

GATEWAY = "gw-a"


def acquisition(seed: int) -> AcquisitionInput:
    return AcquisitionInput(acquired_at=T0 + minutes(seed), node_measurement_id=seed, codes=sample_codes(seed),
                            volts_per_code=1.0 / 32768, fs_hz=2.0e6, t0_s=1.0e-5, averaging=16, excitation_hz=85e3,
                            cycles=5, temperature_c=21.5)


def fill(db: Database, nodes: tuple[str, ...] = ("node-a", "node-b"), monitors: int = 2) -> None:
    """Per node: its identity, a baseline cycle, ``monitors`` calm monitor cycles, one with an alert event."""
    for n, node in enumerate(nodes):
        with db.write() as session:
            upsert_node(session, node_info(node), seen_at=T0)
            store_cycle(session, node, CycleRecord(
                acquisition(100 * n), MeasurementKind.BASELINE, {},
                state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.OK), activate_baseline="first"))
        for seed in range(1, monitors + 1):
            event = EventInput("node_online", Severity.INFO, {"seed": seed}, (), uuid.uuid4())
            with db.write() as session:
                store_cycle(session, node, CycleRecord(
                    acquisition(100 * n + seed), MeasurementKind.MONITOR, {},
                    detection=DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK)),
                    (lambda _mid, e=event: [e]) if seed == monitors else None)


@pytest.fixture
def db(sqlite_url: str):
    database = open_database(sqlite_url)
    database.queue_uplink(QueuePolicy("everything"))
    yield database
    database.dispose()


@pytest.fixture
def centre():
    server = ScriptedCentre()
    yield server
    server.close()


def settings(url: str, **overrides) -> UplinkSettings:
    values = dict(url=url, key="gw-key-1", gateway_id=GATEWAY, site="site-1", batch_records=50,
                  backoff_base_s=1.0, backoff_cap_s=8.0, retry_after_max_s=120.0, refusals_max=2, timeout_s=5.0)
    return UplinkSettings(**{**values, **overrides})


def sender_for(db: Database, url: str, **overrides) -> UplinkSender:
    return UplinkSender(settings(url, **overrides), db, stop=threading.Event(), rng=random.Random(7))


def drain(sender: UplinkSender, passes: int = 50) -> None:
    for _ in range(passes):
        with sender.database.session() as session:
            if queue_stats(session).depth == 0:
                return
        sender.run_once()
    raise AssertionError("the queue did not drain")


def pending(db: Database) -> int:
    with db.session() as session:
        return queue_stats(session).depth


def test_the_queue_goes_up_gzipped_with_the_key_in_order_per_node_and_is_marked_sent(db, centre):
    fill(db)
    sender = sender_for(db, centre.url, batch_records=4)
    drain(sender)
    first = centre.seen[0]
    assert first.headers["authorization"] == "Bearer gw-key-1" and first.headers["content-encoding"] == "gzip"
    with db.session() as session:
        rows = session.scalars(select(UplinkRow).order_by(UplinkRow.id)).all()
        assert {row.status for row in rows} == {UplinkStatus.SENT}
        queue_order = {}
        for row in rows:
            queue_order.setdefault(row.node_id, []).append(record_uid(GATEWAY, row.kind.value, row.ref))
        stored = {m.id: m.traces_sha256 for m in session.scalars(select(MeasurementRow))}
    sent_order = {}
    for seen in centre.seen:
        for record in seen.batch.records:
            sent_order.setdefault(record.node_id, []).append(record.uid)
    assert sent_order == queue_order  # every record once, each node's in the order it was written
    measurements = [r for r in centre.held.values() if isinstance(r, MeasurementRecord)]
    assert {int(r.uid.rsplit("/", 1)[1]): r.traces.sha256 for r in measurements} == stored
    assert all(r.traces.data is not None for r in measurements)
    assert sender.stats.records == len(rows) and sender.stats.duplicates == 0


def test_a_busy_centre_is_left_alone_for_its_retry_after_and_nothing_is_marked_sent(db, centre):
    fill(db, nodes=("node-a",), monitors=1)
    centre.script = [Reply(503, {"Retry-After": "60"}), Reply(429, {"Retry-After": "100000"})]
    sender = sender_for(db, centre.url)
    before = pending(db)
    assert 60.0 <= sender.run_once() <= 120.0  # Retry-After is a lower bound of the wait
    assert sender.run_once() == 120.0  # and honoured up to retry_after_max_s
    assert pending(db) == before and sender.stats.failures == 2
    assert sender.run_once() == 0.0 and pending(db) == 0


def test_an_unreachable_centre_is_retried_with_growing_jittered_waits_up_to_the_cap(db):
    fill(db, nodes=("node-a",), monitors=1)
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{probe.getsockname()[1]}"
    sender = sender_for(db, url)
    waits = [sender.run_once() for _ in range(6)]
    ceilings = [min(8.0, 2.0**i) for i in range(6)]
    assert all(0.0 <= wait <= ceiling for wait, ceiling in zip(waits, ceilings, strict=True))
    assert len(set(waits)) > 1  # jittered, not a fixed schedule
    assert "ConnectError" in (sender.stats.last_error or "") and pending(db) > 0


def test_a_record_the_centre_refuses_is_set_aside_after_refusals_max_and_the_rest_goes_up(db, centre):
    fill(db, nodes=("node-a",), monitors=1)
    centre.script = [bad_record(2), bad_record(2)]
    sender = sender_for(db, centre.url)
    drain(sender)
    with db.session() as session:
        (refused,) = session.scalars(select(UplinkRow).where(UplinkRow.status == UplinkStatus.REFUSED)).all()
        assert refused.refusals == 2 and "bad value" in refused.last_error
        refused_uid = record_uid(GATEWAY, refused.kind.value, refused.ref)
    assert refused_uid not in centre.held and sender.stats.refused == 1
    with db.session() as session:
        assert queue_stats(session).refused == 1


def test_a_batch_too_large_is_halved_until_it_fits(db, centre):
    fill(db, nodes=("node-a",), monitors=3)
    centre.script = [Reply(413), Reply(413)]
    sender = sender_for(db, centre.url, batch_records=8)
    sender.run_once()
    assert sender.limit == 4
    sender.run_once()
    assert sender.limit == 2
    drain(sender)
    assert [len(seen.batch.records) for seen in centre.seen[:3]] == [8, 4, 2]
    assert sender.limit == 8  # grown back once batches are stored


def test_a_wrong_key_backs_off_and_says_so(db, centre):
    fill(db, nodes=("node-a",), monitors=1)
    centre.script = [Reply(401, {}, {"title": "Unauthorized", "detail": "unknown or revoked API key"})]
    sender = sender_for(db, centre.url)
    assert 0.0 <= sender.run_once() <= 1.0
    assert sender.stats.last_error == "HTTP 401 unknown or revoked API key" and pending(db) > 0


def test_flagged_traces_sends_calm_measurements_without_their_traces(sqlite_url, centre):
    db = open_database(sqlite_url)
    db.queue_uplink(QueuePolicy("flagged_traces"))
    fill(db, nodes=("node-a",), monitors=2)
    drain(sender_for(db, centre.url))
    traces = {r.measurement_kind + str(r.node_measurement_id): r.traces.data is not None
              for r in centre.held.values() if isinstance(r, MeasurementRecord)}
    assert traces == {"baseline0": True, "monitor1": False, "monitor2": False}
    db.dispose()


def test_a_batch_is_a_valid_ingest_batch_within_the_body_limit(db, centre):
    fill(db, nodes=("node-a",), monitors=3)
    sender = sender_for(db, centre.url, batch_bytes=10_000)  # about one measurement with traces
    sizes = []
    while pending(db):
        sender.run_once()
        sizes.append(len(centre.seen[-1].batch.model_dump_json()))
    assert len(centre.seen) > 2 and centre.seen[0].batch.gateway_id == GATEWAY
    assert all(size <= 10_000 or len(seen.batch.records) == 1 for size, seen in zip(sizes, centre.seen, strict=True))
    assert centre.url + INGEST_PATH == sender.endpoint
