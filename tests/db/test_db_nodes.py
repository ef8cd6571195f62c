"""What an admin decides about a node: its label, location and notes, and decommissioning."""
from __future__ import annotations

from datetime import timedelta

import pytest

from db.errors import NotFound, StateConflict
from db.nodes import (
    decommission_node,
    get_node,
    is_decommissioned,
    list_nodes,
    recommission_node,
    update_node_details,
    upsert_node,
)
from tests.support.db_fixtures import T0, node_info


@pytest.fixture
def fleet(any_db):
    with any_db.write() as session:
        for node_id in ("node-a", "node-b"):
            upsert_node(session, node_info(node_id), seen_at=T0)
    return any_db


def test_details_change_only_what_is_given_and_record_who_and_when(fleet):
    with fleet.write() as session:
        update_node_details(session, "node-a", {"label": "Line 3 east", "location": "rack 2"}, who="admin:kim", now=T0)
    with fleet.write() as session:
        update_node_details(session, "node-a", {"location": None}, who="admin:lee", now=T0 + timedelta(hours=1))
    with fleet.session() as session:
        node = get_node(session, "node-a")
        assert (node.label, node.location, node.notes) == ("Line 3 east", None, None)
        assert node.details_updated_by == "admin:lee" and node.details_updated_at == T0 + timedelta(hours=1)


def test_details_refuse_fields_that_are_not_details(fleet):
    with fleet.write() as session, pytest.raises(ValueError, match="state"):
        update_node_details(session, "node-a", {"state": "ok"}, who="admin:kim")


def test_a_decommissioned_node_leaves_the_fleet_list_but_keeps_its_record(fleet):
    with fleet.write() as session:
        decommission_node(session, "node-b", who="admin:kim", reason="line removed", now=T0)
    with fleet.session() as session:
        assert [n.node_id for n in list_nodes(session, include_decommissioned=False)] == ["node-a"]
        assert [n.node_id for n in list_nodes(session)] == ["node-a", "node-b"]
        assert is_decommissioned(session, "node-b") and not is_decommissioned(session, "node-a")
        node = get_node(session, "node-b")
        assert (node.decommissioned_by, node.decommission_reason, node.decommissioned_at) == ("admin:kim", "line removed", T0)


def test_decommissioning_twice_conflicts_and_keeps_the_first_decision(fleet):
    with fleet.write() as session:
        decommission_node(session, "node-b", who="admin:kim", reason="line removed", now=T0)
    with fleet.write() as session, pytest.raises(StateConflict, match="admin:kim"):
        decommission_node(session, "node-b", who="admin:lee", reason="again")
    with fleet.session() as session:
        assert get_node(session, "node-b").decommissioned_by == "admin:kim"


def test_recommissioning_puts_the_node_back_and_conflicts_for_one_in_service(fleet):
    with fleet.write() as session:
        decommission_node(session, "node-b", who="admin:kim", reason="moved", now=T0)
    with fleet.write() as session:
        recommission_node(session, "node-b")
    with fleet.session() as session:
        assert not is_decommissioned(session, "node-b")
        assert get_node(session, "node-b").decommission_reason is None
    with fleet.write() as session, pytest.raises(StateConflict, match="in service"):
        recommission_node(session, "node-b")


def test_an_unknown_node_is_not_found(fleet):
    with fleet.write() as session, pytest.raises(NotFound):
        decommission_node(session, "node-z", who="admin:kim", reason="?")
    with fleet.session() as session:
        assert not is_decommissioned(session, "node-z")
