"""What an operator changes through the gateway's API is queued for the uplink in the same transaction
(issue 17, a replication gap): a node's details and (re)commissioning queue its record, a baseline set
queues the one it deactivated and the new one — but only when the gateway that owns the database
replicates, which the API's process reads from the database (``uplink_config``)."""
from __future__ import annotations

import pytest
from sqlalchemy import select

from db.baselines import add_library_baseline, set_active_baseline
from db.cycles import store_cycle
from db.database import Database, open_database
from db.models import MeasurementKind, NodeRow, UplinkKind, UplinkRow, UplinkStatus
from db.nodes import decommission_node, recommission_node, register_configured_node, update_node_details, upsert_node
from db.records import CycleRecord
from db.uplink_queue import QueuePolicy, mark_sent, next_batch, queue_policy, store_policy
from tests.support.db_fixtures import T0, node_info
from tests.support.uplink_records import acquisition, commission_and_flag, queued


@pytest.fixture
def gateway_and_api(sqlite_url: str):
    """The gateway's handle (told to queue, as the daemon does) and the API's (never told) on one file."""
    gateway = open_database(sqlite_url)
    gateway.queue_uplink(QueuePolicy("flagged_traces"))
    with gateway.write() as session:
        store_policy(session, QueuePolicy("flagged_traces"), now=T0)
    api = open_database(sqlite_url)
    yield gateway, api
    api.dispose()
    gateway.dispose()


def send_everything(db: Database) -> None:
    with db.write() as session:
        mark_sent(session, [row.id for row in next_batch(session, limit=100)])


def pending(db: Database) -> list[tuple[str, str, bool]]:
    with db.session() as session:
        rows = session.scalars(select(UplinkRow).where(UplinkRow.status == UplinkStatus.PENDING).order_by(UplinkRow.id))
        return [(row.kind.value, row.ref, row.with_traces) for row in rows]


def revision(db: Database, node_id: str = "node-a") -> int:
    with db.session() as session:
        return session.get(NodeRow, node_id).revision


def test_the_apis_process_queues_exactly_when_the_gateway_stored_that_it_replicates(sqlite_url):
    api = open_database(sqlite_url)
    with api.write() as session:
        assert queue_policy(session) is None  # no gateway said it replicates
        store_policy(session, QueuePolicy("everything"), now=T0)
    with api.write() as session:
        assert queue_policy(session) == QueuePolicy("everything")
        store_policy(session, None)  # the gateway restarted without [uplink]
    with api.write() as session:
        assert queue_policy(session) is None
    told = open_database(sqlite_url)
    told.queue_uplink(None)  # the gateway's own handle goes by what it was told, not by the table
    with api.write() as session:
        store_policy(session, QueuePolicy("everything"), now=T0)
    with told.write() as session:
        assert queue_policy(session) is None
    told.dispose()
    api.dispose()


def test_details_and_decommissioning_queue_the_node_record_and_raise_its_revision(gateway_and_api):
    gateway, api = gateway_and_api
    with gateway.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
    send_everything(gateway)
    before = revision(gateway)

    with api.write() as session:
        update_node_details(session, "node-a", {"label": "Line 3", "location": "east loop"}, who="alice")
    assert pending(gateway) == [("node", "node-a", False)]
    with api.write() as session:  # a record still pending carries the latest view: no second one
        decommission_node(session, "node-a", who="alice", reason="pipe replaced")
    assert pending(gateway) == [("node", "node-a", False)]
    assert revision(gateway) == before + 2

    send_everything(gateway)
    with api.write() as session:
        recommission_node(session, "node-a")
    assert pending(gateway) == [("node", "node-a", False)] and revision(gateway) == before + 3


def test_without_an_uplink_an_admins_change_queues_nothing(sqlite_db):
    with sqlite_db.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        update_node_details(session, "node-a", {"label": "Line 3"}, who="alice")
        decommission_node(session, "node-a", who="alice", reason="gone")
    assert queued(sqlite_db) == []
    assert revision(sqlite_db) == 3  # the INFO, the details, the decommissioning: counted anyway


def test_a_node_that_never_answered_is_not_queued_when_decommissioned(gateway_and_api):
    gateway, api = gateway_and_api
    with gateway.write() as session:
        register_configured_node(session, "node-z", port_url="tcp://127.0.0.1:1", now=T0)
    with api.write() as session:
        decommission_node(session, "node-z", who="alice", reason="never installed")
    assert pending(gateway) == []


def test_a_baseline_set_at_the_api_queues_the_deactivated_one_then_the_new_one_after_its_traces(gateway_and_api):
    gateway, api = gateway_and_api
    _base_id, monitor_id = commission_and_flag(gateway)  # flagged: the monitor went up with its traces
    with gateway.write() as session:  # a calm record: under flagged_traces it goes up without its traces
        calm_id = store_cycle(session, "node-a", CycleRecord(acquisition(7), MeasurementKind.MONITOR, {})).measurement_id
    assert queued(gateway)[-1] == ("measurement", "node-a", str(calm_id), False)
    send_everything(gateway)
    with gateway.session() as session:
        first_baseline = session.scalars(select(UplinkRow.ref).where(UplinkRow.kind == UplinkKind.BASELINE)).one()

    with api.write() as session:
        new = set_active_baseline(session, "node-a", monitor_id, created_by="alice", reason="after the repair")
    assert pending(gateway) == [("baseline", first_baseline, False), ("baseline", str(new.id), False)]
    send_everything(gateway)

    with api.write() as session:
        library = add_library_baseline(session, "node-a", calm_id, created_by="alice", reason="warm day")
    assert pending(gateway) == [("measurement", str(calm_id), True), ("baseline", str(library.id), False)]


def test_a_node_changed_while_its_record_was_on_the_way_is_queued_again(gateway_and_api):
    gateway, api = gateway_and_api
    with gateway.write() as session:
        upsert_node(session, node_info(), seen_at=T0)
        rows = next_batch(session, limit=10)
        sent_revision = session.get(NodeRow, "node-a").revision
    with api.write() as session:  # the record is pending (being sent): this change queues none
        decommission_node(session, "node-a", who="alice", reason="pipe replaced")
    assert len(pending(gateway)) == 1
    with gateway.write() as session:
        mark_sent(session, [row.id for row in rows], node_revisions={"node-a": sent_revision})
    assert pending(gateway) == [("node", "node-a", False)]
    with gateway.write() as session:  # acknowledged at the latest revision: nothing more
        rows = next_batch(session, limit=10)
        mark_sent(session, [row.id for row in rows], node_revisions={"node-a": sent_revision + 1})
    assert pending(gateway) == []


def test_a_recommissioning_that_reaches_the_centre_restarts_the_centres_watch_of_the_node(sqlite_db):
    from datetime import timedelta

    from db.ingest import ingest_batch
    from tests.support.ingest_batches import batch_of, node_record

    out = dict(decommissioned_at=T0 + timedelta(hours=1), decommissioned_by="alice", decommission_reason="repair")

    def arrives(record, at):
        with sqlite_db.write() as session:
            ingest_batch(session, batch_of("gw-n1", "north", [record]), key_site="north", now=at)
        with sqlite_db.session() as session:
            return session.get(NodeRow, "node-a").watched_since

    assert arrives(node_record("gw-n1", "node-a", revision=1), T0) == T0  # its first answer
    assert arrives(node_record("gw-n1", "node-a", revision=2, **out), T0 + timedelta(hours=1)) == T0
    back = T0 + timedelta(days=3)
    assert arrives(node_record("gw-n1", "node-a", revision=3), back) == back  # watched again from its return
    assert arrives(node_record("gw-n1", "node-a", revision=4, label="Line 3"), back + timedelta(hours=1)) == back
