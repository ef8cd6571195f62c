"""Outbox queries on SQLite and PostgreSQL: one head per node, compare-and-set claims, results recorded."""
from __future__ import annotations

from datetime import timedelta

import pytest

from alerts.config import AlertingSettings
from alerts.events import STATE_KINDS, state_change_event
from alerts.outbox import (
    claim,
    delivery_counts,
    is_due,
    latest_delivered,
    mark_delivered,
    mark_failed,
    pending_heads,
)
from db.clock import utc_now
from db.measurements import add_event_once
from db.models import DeliveryStatus
from db.nodes import upsert_node
from tests.support.db_fixtures import T0, node_info

SETTINGS = AlertingSettings.model_validate({"sinks": [{"type": "mqtt", "name": "m", "host": "127.0.0.1"}]})


@pytest.fixture
def db(any_db):
    with any_db.write() as session:
        for node_id in ("n1", "n2"):
            upsert_node(session, node_info(node_id), seen_at=T0)
    return any_db


def put(db, node_id, measurement_id, to_state="damage", from_state="ok", minutes=0):
    event = state_change_event(SETTINGS, node_id=node_id, from_state=from_state, to_state=to_state,
                               measurement_id=measurement_id, peak_di=1.0, threshold=0.5)
    with db.write() as session:
        assert add_event_once(session, event, node_id=node_id, now=T0 + timedelta(minutes=minutes))
        assert not add_event_once(session, event, node_id=node_id)  # the same fact is never queued twice
    return event


def test_only_the_oldest_pending_event_of_each_node_is_offered(db):
    first_n1 = put(db, "n1", 1, minutes=1)
    put(db, "n1", 2, from_state="damage", to_state="ok", minutes=2)
    first_n2 = put(db, "n2", 3, minutes=3)
    with db.session() as session:
        heads = pending_heads(session, "m")
    assert [h.event_id for h in heads] == [first_n1.id, first_n2.id]
    assert all(is_due(h, utc_now()) for h in heads)


def test_a_claim_is_taken_once_and_its_lease_hides_the_delivery_until_it_runs_out(db):
    put(db, "n1", 1)
    with db.session() as session:
        head, = pending_heads(session, "m")
    now = utc_now()
    with db.write() as session:
        assert claim(session, head, now=now, lease_s=30)
    with db.write() as session:
        assert not claim(session, head, now=now, lease_s=30)  # stale read: someone else has it
    with db.session() as session:
        leased, = pending_heads(session, "m")
    assert leased.attempts == 1 and not is_due(leased, now + timedelta(seconds=29))
    assert is_due(leased, now + timedelta(seconds=31))  # a crashed claimer's delivery comes back


def test_results_are_recorded_and_the_newest_delivered_state_per_node_is_known(db):
    raised = put(db, "n1", 1, minutes=1)
    cleared = put(db, "n1", 2, from_state="damage", to_state="ok", minutes=2)
    other = put(db, "n2", 3, minutes=3)
    with db.session() as session:
        heads = {h.event_id: h for h in pending_heads(session, "m")}
    with db.write() as session:
        assert mark_delivered(session, heads[raised.id].delivery_id)
        assert mark_failed(session, heads[other.id].delivery_id, "boom", retry_at=None)
        assert not mark_delivered(session, heads[other.id].delivery_id)  # dead stays dead
    with db.session() as session:
        assert [i.event_id for i in latest_delivered(session, "m", STATE_KINDS)] == [raised.id]
        assert delivery_counts(session) == {("m", DeliveryStatus.DELIVERED): 1, ("m", DeliveryStatus.DEAD): 1,
                                            ("m", DeliveryStatus.PENDING): 1}
        nxt, = [h for h in pending_heads(session, "m") if h.node_id == "n1"]
    assert nxt.event_id == cleared.id
