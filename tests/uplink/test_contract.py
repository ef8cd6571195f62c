"""The uplink's wire contract: what a well-formed batch is, and what is refused before anything is stored."""
from __future__ import annotations

import base64
import hashlib
import uuid
import zlib
from datetime import UTC, datetime, timedelta

import pytest
from pydantic import ValidationError

from tests.support.ingest_batches import node_record
from uplink.contract import (
    MAX_RECORDS_PER_BATCH,
    BaselineView,
    Blob,
    DetectionRecord,
    IngestBatch,
    MeasurementRecord,
    NodeRecord,
    StoredTraces,
    TraceAnswers,
    node_record_is_stale,
    record_uid,
    resent_baseline,
    resent_measurement,
)

T0 = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)
STORED = zlib.compress(bytes(range(256)) * 8)


def node(gateway: str = "gw-a", node_id: str = "node-1") -> dict:
    return {"kind": "node", "uid": record_uid(gateway, "node", node_id), "node_id": node_id, "firmware": "1.0",
            "protocol_version": 1, "n_channels": 8, "fs_hz": 1e6, "geometry": {"circumference_mm": 200.0},
            "first_seen_at": T0.isoformat(), "last_seen_at": T0.isoformat(), "online": True, "state": "ok"}


def measurement(gateway: str = "gw-a", local_id: int = 1, data: bytes | None = STORED) -> dict:
    traces = Blob.of(data, dtype="<i2", sha256=hashlib.sha256(STORED).hexdigest(), nbytes=len(STORED))
    return {"kind": "measurement", "uid": record_uid(gateway, "measurement", local_id), "node_id": "node-1",
            "measurement_kind": "monitor", "acquired_at": T0.isoformat(), "node_measurement_id": local_id,
            "settings": {"averaging": 4, "fs_hz": 1e6, "t0_s": 0.0, "n_channels": 8, "n_samples": 256,
                         "volts_per_code": 1e-4, "excitation_hz": 5e4, "cycles": 5},
            "traces": traces.model_dump()}


def detection(gateway: str = "gw-a") -> dict:
    return {"kind": "detection", "uid": record_uid(gateway, "detection", 1), "node_id": "node-1",
            "measurement_uid": record_uid(gateway, "measurement", 1), "peak_di": 0.3, "threshold": 0.1,
            "state": "damage", "created_at": T0.isoformat()}


def batch(*records: dict, gateway: str = "gw-a") -> dict:
    return {"gateway_id": gateway, "site": "north", "batch_id": str(uuid.uuid4()), "records": list(records)}


def test_a_batch_round_trips_through_json_with_each_record_parsed_by_its_kind():
    parsed = IngestBatch.model_validate_json(IngestBatch.model_validate(batch(node(), measurement(), detection()))
                                             .model_dump_json())
    assert [type(r) for r in parsed.records] == [NodeRecord, MeasurementRecord, DetectionRecord]
    assert parsed.records[1].traces.raw() == STORED


def test_traces_may_be_omitted_but_their_checksum_still_travels():
    parsed = IngestBatch.model_validate(batch(measurement(data=None)))
    traces = parsed.records[0].traces
    assert traces.data is None and traces.sha256 == hashlib.sha256(STORED).hexdigest()
    with pytest.raises(ValueError, match="not sent"):
        traces.raw()


def test_a_uid_under_another_gateways_name_is_refused():
    with pytest.raises(ValidationError, match=r"record 1: uid 'gw-b/measurement/1' must be gw-a/measurement/"):
        IngestBatch.model_validate(batch(node(), measurement(gateway="gw-b")))


def test_a_uid_of_another_kind_is_refused():
    wrong = {**detection(), "uid": "gw-a/measurement/9"}
    with pytest.raises(ValidationError, match="must be gw-a/detection/"):
        IngestBatch.model_validate(batch(wrong))


def test_the_same_uid_twice_in_one_batch_is_refused():
    with pytest.raises(ValidationError, match="appears twice"):
        IngestBatch.model_validate(batch(measurement(), measurement()))


def test_traces_that_do_not_match_their_checksum_are_refused():
    damaged = measurement()
    damaged["traces"]["data"] = base64.b64encode(STORED[:-1] + b"x").decode()
    with pytest.raises(ValidationError, match="does not match its sha256"):
        IngestBatch.model_validate(batch(damaged))


def test_traces_whose_length_differs_from_nbytes_are_refused():
    short = measurement()
    short["traces"]["nbytes"] += 1
    with pytest.raises(ValidationError, match="nbytes says"):
        IngestBatch.model_validate(batch(short))


def test_an_unknown_kind_an_unknown_field_and_a_naive_time_are_refused():
    with pytest.raises(ValidationError, match="does not match any of the expected tags"):
        IngestBatch.model_validate(batch({**node(), "kind": "gossip"}))
    with pytest.raises(ValidationError, match="Extra inputs"):
        IngestBatch.model_validate(batch({**node(), "colour": "blue"}))
    with pytest.raises(ValidationError, match="timezone"):
        IngestBatch.model_validate(batch({**node(), "last_seen_at": "2026-05-01T12:00:00"}))


def test_a_batch_is_bounded_in_records():
    with pytest.raises(ValidationError, match="at least 1"):
        IngestBatch.model_validate(batch())
    many = [{**node(node_id=f"n{i}"), "uid": f"gw-a/node/n{i}"} for i in range(MAX_RECORDS_PER_BATCH + 1)]
    with pytest.raises(ValidationError, match=f"at most {MAX_RECORDS_PER_BATCH}"):
        IngestBatch.model_validate(batch(*many))


# ------------------------------------------------------------------ traces on demand
def stored_traces(*, here: bool, sha256: str = hashlib.sha256(STORED).hexdigest()) -> StoredTraces:
    return StoredTraces(here=here, codec="shuffle-zlib-v1", dtype="<i2", sha256=sha256, nbytes=len(STORED))


def test_a_measurement_resent_with_the_traces_the_centre_lacks_adds_them():
    record = MeasurementRecord.model_validate(measurement())
    assert resent_measurement(stored_traces(here=False), record) == "add_traces"


@pytest.mark.parametrize(("here", "data"), [(True, STORED), (False, None), (True, None)])
def test_a_measurement_resent_otherwise_is_a_duplicate(here, data):
    record = MeasurementRecord.model_validate(measurement(data=data))
    assert resent_measurement(stored_traces(here=here), record) == "duplicate"


@pytest.mark.parametrize("here", [True, False])
def test_traces_that_are_not_the_stored_measurements_are_refused_even_on_a_record_without_them(here):
    record = MeasurementRecord.model_validate(measurement())
    with pytest.raises(ValueError, match="a stored measurement does not change"):
        resent_measurement(stored_traces(here=here, sha256="0" * 64), record)


def test_trace_answers_name_only_the_gateways_own_measurements():
    answer = {"request_id": 4, "measurement_uid": "gw-a/measurement/17", "answer": "held"}
    assert TraceAnswers(gateway_id="gw-a", site="north", answers=[answer]).answers[0].answer == "held"
    with pytest.raises(ValidationError, match="must be gw-b/measurement/<local id>"):
        TraceAnswers(gateway_id="gw-b", site="north", answers=[answer])
    with pytest.raises(ValidationError):
        TraceAnswers(gateway_id="gw-a", site="north", answers=[{**answer, "answer": "maybe"}])
    with pytest.raises(ValidationError):
        TraceAnswers(gateway_id="gw-a", site="north", answers=[])


def test_node_records_are_ordered_by_revision_then_last_seen_at():
    later = T0 + timedelta(minutes=1)
    admin_change = node_record("gw-n1", "pipe-1", seen_at=T0, revision=3)
    assert not node_record_is_stale(2, T0, admin_change)  # an admin's change, last_seen_at unmoved: it wins
    assert not node_record_is_stale(3, T0, admin_change)  # the same view again: not stale (a duplicate)
    assert node_record_is_stale(4, T0, admin_change)
    assert node_record_is_stale(3, later, admin_change)  # same revision, older last_seen_at
    assert not node_record_is_stale(None, None, admin_change)  # nothing held yet
    assert not node_record_is_stale(None, T0, node_record("gw-n1", "pipe-1", seen_at=later))  # a gateway without revisions
    assert node_record_is_stale(None, later, node_record("gw-n1", "pipe-1", seen_at=T0))


def test_a_resent_baseline_may_only_be_deactivated():
    active = BaselineView("pipe-1", "gw-n1/measurement/1", "gateway", T0, "commissioning", True, None)
    off = BaselineView("pipe-1", "gw-n1/measurement/1", "gateway", T0, "commissioning", False, T0 + timedelta(days=1))
    assert resent_baseline(active, off) == "deactivate"
    assert resent_baseline(active, active) == "duplicate"
    assert resent_baseline(off, off) == "duplicate"
    assert resent_baseline(off, active) == "stale"  # an older view: the gateway never re-activates a baseline
    assert resent_baseline(off, BaselineView(*[*vars(off).values()][:6], T0 + timedelta(days=2))) == "duplicate"
    for name, value in (("measurement_uid", "gw-n1/measurement/2"), ("reason", "edited"), ("created_by", "bob"),
                        ("created_at", T0 + timedelta(seconds=1)), ("node_id", "pipe-2")):
        changed = BaselineView(**{**vars(off), name: value})
        with pytest.raises(ValueError, match=name):
            resent_baseline(active, changed)
