"""Fleet-wide queries at a central site: a summary per site, then nodes filtered by site, gateway and
state, paged; which nodes are damaged, where and since when. Data arrives the way gateways send it."""
from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta

import pytest

from tests.support.central_site import Centre, serve_centre
from tests.support.db_fixtures import T0
from tests.support.ingest_batches import (
    batch_of,
    detection_record,
    measurement_record,
    node_record,
    state_change_record,
)
from uplink.contract import Record


def damaged_node(gateway: str, node_id: str, local_id: int) -> list[Record]:
    """A node that read damage at measurement ``local_id`` (at T0 + local_id s)."""
    return [node_record(gateway, node_id, seen_at=T0 + timedelta(seconds=local_id), state="damage"),
            measurement_record(gateway, node_id, local_id, traces=False),
            detection_record(gateway, node_id, local_id, local_id, state="damage"),
            state_change_record(gateway, node_id, local_id, local_id)]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Iterator[Centre]:
    url = f"sqlite:///{tmp_path_factory.mktemp('fleet') / 'central.db'}"
    with serve_centre(url) as centre:
        north = [node_record("gw-n1", f"n-{i}") for i in range(5)] + damaged_node("gw-n1", "n-d1", 11)
        north += damaged_node("gw-n1", "n-d2", 12)
        assert centre.post(batch_of("gw-n1", "north", north), centre.north).status_code == 200
        north2 = [node_record("gw-n2", "n2-0")]
        assert centre.post(batch_of("gw-n2", "north", north2), centre.north).status_code == 200
        south = [node_record("gw-s1", f"s-{i}") for i in range(3)]
        assert centre.post(batch_of("gw-s1", "south", south), centre.south).status_code == 200
        yield centre


def test_the_site_summary_puts_sites_with_damage_first(fleet: Centre):
    sites = fleet.get("/fleet/sites").json()
    assert [(s["site"], s["gateways"], s["nodes"], s["flagged"]) for s in sites] == [
        ("north", ["gw-n1", "gw-n2"], 8, 2), ("south", ["gw-s1"], 3, 0)]
    assert sites[0]["by_state"] == {"ok": 6, "damage": 2} and sites[0]["offline"] == 0


def test_which_nodes_are_damaged_where_and_since_when(fleet: Centre):
    page = fleet.get("/fleet/nodes", state="damage").json()
    assert page["next_cursor"] is None
    assert [(n["node_id"], n["site"], n["gateway_id"]) for n in page["items"]] == [
        ("n-d1", "north", "gw-n1"), ("n-d2", "north", "gw-n1")]
    first = page["items"][0]
    assert first["state_since"] == (T0 + timedelta(seconds=11)).isoformat().replace("+00:00", "Z")
    assert (first["latest_detection"]["axial_mm"], first["latest_detection"]["angle_deg"]) == (1500.0, 90.0)


def test_nodes_filter_by_site_and_gateway(fleet: Centre):
    south = fleet.get("/fleet/nodes", site="south").json()["items"]
    assert [n["node_id"] for n in south] == ["s-0", "s-1", "s-2"]
    assert [n["node_id"] for n in fleet.get("/fleet/nodes", gateway_id="gw-n2").json()["items"]] == ["n2-0"]
    both = fleet.get("/fleet/nodes", site="north", state=["damage", "ok"], limit=1000).json()["items"]
    assert len(both) == 8
    assert fleet.get("/fleet/nodes", site="nowhere").json() == {"items": [], "next_cursor": None}


def test_pages_walk_the_whole_fleet_once_in_node_order(fleet: Centre):
    seen: list[str] = []
    cursor = None
    for _ in range(10):  # 11 nodes, 3 a page: 4 pages
        page = fleet.get("/fleet/nodes", limit=3, **({"cursor": cursor} if cursor else {})).json()
        seen += [n["node_id"] for n in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == sorted(seen) and len(seen) == len(set(seen)) == 11
    assert fleet.get("/fleet/nodes", cursor="!!not-a-cursor").status_code == 400


def test_fleet_wide_detections_filter_by_site(fleet: Centre):
    north = fleet.get("/detections", site="north").json()["items"]
    assert sorted(d["node_id"] for d in north) == ["n-d1", "n-d2"]
    assert fleet.get("/detections", site="south").json()["items"] == []
    assert len(fleet.get("/detections", gateway_id="gw-n1").json()["items"]) == 2
