"""Raw traces on demand at the central site: a measurement stored without its traces takes them from a
later upload of the same uid, and only that; the request for them moves requested -> held/pruned ->
received, or -> refused (with why) when the record the gateway re-sent is refused. On SQLite and PostgreSQL (the ingest runs in one transaction on either)."""
from __future__ import annotations

import pytest
from sqlalchemy import select
from sqlalchemy.orm import undefer

from db.database import Database
from db.ingest import IngestRefused, ingest_batch
from db.models import MeasurementRow, TraceRequestStatus
from db.trace_requests import (
    TraceAnswerRefused,
    answer_requests,
    pending_requests,
    refuse_resent,
    request_outcome,
    request_traces_of,
    traces_state,
    traces_status,
)
from tests.support.db_fixtures import store_sample
from tests.support.ingest_batches import batch_of, measurement_record, node_history, node_record

GW = "gw-n1"
UID = f"{GW}/measurement/1"


def store(db: Database, records, site: str = "north"):
    with db.write() as session:
        return ingest_batch(session, batch_of(GW, site, records), key_site=site)


def measurement(db: Database) -> MeasurementRow:
    with db.session() as session:
        row = session.scalars(select(MeasurementRow).options(undefer(MeasurementRow.traces_blob))).one()
        session.expunge(row)
        return row


def ask(db: Database, who: str = "operator-1"):
    with db.write() as session:
        return request_traces_of(session, session.get(MeasurementRow, measurement(db).id), who=who)


def state(db: Database):
    with db.session() as session:
        return traces_state(session, session.get(MeasurementRow, measurement(db).id))


@pytest.mark.parametrize(("here", "from_gateway", "request_status", "status", "outcome"), [
    (True, False, None, "stored", "here"),
    (True, True, TraceRequestStatus.RECEIVED, "received", "here"),
    (False, True, None, "at_gateway", "asked"),
    (False, True, TraceRequestStatus.REQUESTED, "requested", "pending"),
    (False, True, TraceRequestStatus.HELD, "held", "pending"),
    (False, True, TraceRequestStatus.PRUNED, "pruned", "gone"),
    (False, True, TraceRequestStatus.REFUSED, "refused", "asked"),  # the gateway still holds them: ask again
    (False, True, TraceRequestStatus.RECEIVED, "at_gateway", "asked"),  # received, then pruned here: ask again
    (False, False, None, "pruned_here", "gone"),
])
def test_the_status_of_a_measurements_traces_and_what_asking_for_them_does(here, from_gateway, request_status,
                                                                           status, outcome):
    assert traces_status(here=here, from_gateway=from_gateway, request=request_status) == status
    assert request_outcome(status) == outcome


def test_requested_traces_arrive_on_the_stored_record_and_a_replay_changes_nothing(any_db: Database):
    store(any_db, node_history(GW, "pipe-1", 1, 1, traces=False))
    assert measurement(any_db).traces_blob is None and state(any_db).status == "at_gateway"

    outcome, asked = ask(any_db)
    assert (outcome, asked.status, asked.requested_by, asked.measurement_uid) == ("asked", "requested", "operator-1",
                                                                                 UID)
    assert ask(any_db, who="someone-else")[0] == "pending"  # asked once: the first request stands
    with any_db.session() as session:
        [pending] = pending_requests(session, site="north", gateway_id=GW, limit=10)
        assert pending.measurement_uid == UID and pending_requests(session, site="south", gateway_id=GW, limit=10) == []
    with any_db.write() as session:
        assert answer_requests(session, [(pending.id, UID, "held")], site="north", gateway_id=GW) == 1
    assert state(any_db).status == "held" and state(any_db).answered_at is not None

    with_traces = measurement_record(GW, "pipe-1", 1)
    outcome_of_upload = store(any_db, [node_record(GW, "pipe-1"), with_traces])
    assert (outcome_of_upload.accepted, outcome_of_upload.duplicates) == (1, 1)  # the node unchanged: a duplicate
    row = measurement(any_db)
    assert row.traces_blob == with_traces.traces.raw() and row.traces_pruned_at is None
    assert state(any_db).status == "received" and state(any_db).received_at is not None
    assert ask(any_db)[0] == "here"

    replay = store(any_db, [with_traces])
    assert (replay.accepted, replay.duplicates) == (0, 1)
    with any_db.write() as session:  # a late answer changes nothing
        assert answer_requests(session, [(pending.id, UID, "pruned")], site="north", gateway_id=GW) == 0
    assert state(any_db).status == "received"


def test_traces_that_are_not_the_stored_measurements_are_refused(any_db: Database):
    store(any_db, node_history(GW, "pipe-1", 1, 1, traces=False))
    other = measurement_record(GW, "pipe-1", 2).model_copy(update={"uid": UID})  # another acquisition's traces
    with pytest.raises(IngestRefused) as refused:
        store(any_db, [other])
    assert refused.value.reason == "invalid" and refused.value.index == 0
    assert "a stored measurement does not change" in refused.value.error
    assert measurement(any_db).traces_blob is None


def refused_upload(db: Database, record, site: str = "north") -> str:
    """Send ``record`` as the gateway re-sending it; it must be refused. What the centre notes, as the
    ingest route does (the batch rolled back, then the refusal in a transaction of its own)."""
    with pytest.raises(IngestRefused) as refused:
        store(db, [record], site=site)
    with db.write() as session:
        refuse_resent(session, record.uid, f"HTTP 422 ingest-bad-record: {refused.value.error}", site=site)
    return refused.value.error


def test_a_held_request_whose_resent_record_is_refused_ends_refused_with_why_and_can_be_asked_again(any_db: Database):
    store(any_db, node_history(GW, "pipe-1", 1, 1, traces=False))
    ask(any_db)
    with any_db.write() as session:
        [pending] = pending_requests(session, site="north", gateway_id=GW, limit=1)
        answer_requests(session, [(pending.id, UID, "held")], site="north", gateway_id=GW)
    assert state(any_db).status == "held"

    # Not this measurement's traces (a checksum, a length that is not the one stored): refused, and the request says so.
    other = measurement_record(GW, "pipe-1", 2).model_copy(update={"uid": UID})
    why = refused_upload(any_db, other, site="south")  # another site's key cannot end north's request
    assert state(any_db).status == "held"
    why = refused_upload(any_db, other)
    refused = state(any_db)
    assert refused.status == "refused" and refused.refused_at is not None
    assert refused.refusal == f"HTTP 422 ingest-bad-record: {why}" and "a stored measurement does not change" in why
    assert (refused.requested_by, refused.answered_at) == ("operator-1", state(any_db).answered_at)
    assert measurement(any_db).traces_blob is None and measurement(any_db).traces_pruned_at is not None
    with any_db.session() as session:  # nothing left for the gateway to answer
        assert pending_requests(session, site="north", gateway_id=GW, limit=10) == []

    # The gateway tries the refused record again: the first refusal stands; a late answer changes nothing.
    with any_db.write() as session:
        assert not refuse_resent(session, UID, "HTTP 422 ingest-bad-record: again", site="north")
        assert answer_requests(session, [(pending.id, UID, "held")], site="north", gateway_id=GW) == 0
    assert (state(any_db).refusal, state(any_db).refused_at) == (refused.refusal, refused.refused_at)

    # Asked again (the cause put right): the request starts over, and the right traces end it received.
    outcome, again = ask(any_db, who="operator-2")
    assert (outcome, again.status, again.requested_by) == ("asked", "requested", "operator-2")
    assert (again.refusal, again.refused_at, again.answered_at) == (None, None, None)
    with any_db.write() as session:
        assert answer_requests(session, [(pending.id, UID, "held")], site="north", gateway_id=GW) == 1
    right = measurement_record(GW, "pipe-1", 1)
    assert store(any_db, [right]).accepted == 1
    received = state(any_db)
    assert (received.status, received.refusal, received.refused_at) == ("received", None, None)
    assert measurement(any_db).traces_blob == right.traces.raw()


def test_only_a_refused_measurement_awaiting_its_traces_ends_a_request(any_db: Database):
    store(any_db, node_history(GW, "pipe-1", 1, 1, traces=False))
    with any_db.write() as session:
        assert not refuse_resent(session, UID, "x", site="north")  # no request
        assert not refuse_resent(session, f"{GW}/detection/1", "x", site="north")  # not a measurement
        assert not refuse_resent(session, f"{GW}/measurement/99", "x", site="north")  # not held here
    ask(any_db)
    with any_db.write() as session:
        assert refuse_resent(session, UID, "y" * 5000, site="north")  # requested, the answer lost: refused too
    assert state(any_db).status == "refused" and state(any_db).refusal == "y" * 2000  # bounded


def test_a_gateway_answers_only_its_own_requests(any_db: Database):
    store(any_db, node_history(GW, "pipe-1", 1, 1, traces=False))
    ask(any_db)
    with any_db.session() as session:
        request_id = pending_requests(session, site="north", gateway_id=GW, limit=1)[0].id
    with any_db.write() as session, pytest.raises(TraceAnswerRefused, match="not one of gateway 'gw-s1'"):
        answer_requests(session, [(request_id, UID, "pruned")], site="north", gateway_id="gw-s1")
    with any_db.write() as session, pytest.raises(TraceAnswerRefused, match="is for"):
        answer_requests(session, [(request_id, f"{GW}/measurement/9", "pruned")], site="north", gateway_id=GW)
    with any_db.write() as session:
        assert answer_requests(session, [(request_id, UID, "pruned")], site="north", gateway_id=GW) == 1
    assert state(any_db).status == "pruned"
    assert ask(any_db)[0] == "gone"


def test_a_measurement_of_this_site_itself_cannot_be_requested_once_pruned(any_db: Database):
    with any_db.write() as session:
        row = store_sample(session, "node-a")
        assert traces_state(session, row).status == "stored"
        row.traces_blob, row.traces_pruned_at = None, row.stored_at
        session.flush()
        assert request_traces_of(session, row, who="op")[0] == "gone"
        assert traces_state(session, row).status == "pruned_here"
