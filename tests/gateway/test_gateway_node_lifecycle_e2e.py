"""The gateway against mock nodes that reboot into other power-up settings, answer as another node or
cannot take the configured record length: real processes on ptys, a real SQLite file."""
from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select

from db.database import open_database
from db.measurements import load_traces
from db.models import DetectionRow, DiMapRow, EventRow, MapSource, MeasurementRow, NodeRow
from tests.support.process_harness import (
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]

CONFIGURED = (10, 6000, 85000.0)  # averaging, n_samples, excitation_hz: the gateway's defaults
POWER_UP = (1, 5000, 60000.0)  # what the node comes back with after a reboot


def power_up_node(node_id: str, seed: int, *, reboot_every_s: float, protocol_version: int = 2) -> str:
    averaging, n_samples, excitation_hz = POWER_UP
    text = scenario_node(node_id, seed)
    text += f"[nodes.power_up]\naveraging = {averaging}\nn_samples = {n_samples}\nexcitation_hz = {excitation_hz}\n"
    text += f"[nodes.faults]\nreboot_every_s = {reboot_every_s}\n"
    if protocol_version != 2:
        text += f"protocol_version = {protocol_version}\n"
    return text


def read(db_url: str, fn):
    db = open_database(db_url, upgrade=False)
    try:
        with db.session() as s:
            return fn(s)
    finally:
        db.dispose()


def run_fleet(tmp_path: Path, scenario_text: str, link_ids: list[str], nodes: list[dict]):
    """Mock nodes on ptys and the gateway on them. Each of ``nodes`` is a gateway node's settings
    with ``id``; ``link`` names the mock node whose port it is given (default: its own id)."""
    scenario = tmp_path / "s.toml"
    scenario.write_text(scenario_text)
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path)
    wait_for_links(links, link_ids, mock)
    db_path = tmp_path / "gateway.db"
    config = tmp_path / "gateway.toml"
    configured = []
    for node in nodes:
        rest = {k: v for k, v in node.items() if k not in ("id", "link")}
        configured.append(gateway_node(node["id"], links, url=str(links / node.get("link", node["id"])), **rest))
    config.write_text(gateway_config(db_path, configured))
    return mock, start_gateway(config, tmp_path), f"sqlite:///{db_path}"


def settings_of(row: MeasurementRow) -> tuple[int, int, float]:
    return row.averaging, row.n_samples, row.excitation_hz


@pytest.mark.parametrize("protocol_version", [2, 1])
def test_a_node_rebooted_mid_run_with_other_power_up_defaults_is_reconfigured_and_imaged_correctly(
    tmp_path, protocol_version
):
    mock, gw, url = run_fleet(tmp_path, power_up_node("node-r", 11, reboot_every_s=5.0,
                                                      protocol_version=protocol_version),
                              ["node-r"], [{"id": "node-r"}])

    def reboots_then_imaged():
        def check(s):
            node = s.get(NodeRow, "node-r")
            if node is None or node.reboots < 2:
                return False
            after = s.scalars(select(DetectionRow).join(MeasurementRow, DetectionRow.measurement_id == MeasurementRow.id)
                              .where(MeasurementRow.boot_id == node.boot_id, DetectionRow.peak_di.is_not(None))).all()
            return len(after) >= 2
        return read(url, check)

    try:
        wait_until(reboots_then_imaged, 180, 0.5, what="two reboots noticed and records imaged after the last")
    finally:
        gw.close()
        mock.close()
    log = gw.stderr
    assert "node rebooted (boot id" in log and "Traceback" not in log

    def verify(s):
        node = s.get(NodeRow, "node-r")
        assert node.reboots >= 2 and node.link_problems == [] and node.reported_node_id == "node-r"
        assert node.applied_settings["averaging"] == CONFIGURED[0]
        rows = s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == "node-r")).all()
        assert len({r.boot_id for r in rows}) >= 2  # records from before and after a reboot (a loaded machine
        # may see the first reboot before the first record is stored)
        for row in rows:
            assert settings_of(row) in (CONFIGURED, POWER_UP), settings_of(row)
            assert load_traces(row).shape[1] == row.n_samples  # what the node said is what it sent
            if protocol_version == 1:
                assert settings_of(row) == CONFIGURED  # a v1 record after an unseen reboot is dropped
        by_id = {r.id: r for r in rows}
        for detection in s.scalars(select(DetectionRow).where(DetectionRow.node_id == "node-r")):
            record = by_id[detection.measurement_id]
            if detection.peak_di is not None:  # imaged: only against a baseline of the same settings
                assert settings_of(by_id[detection.baseline_measurement_id]) == settings_of(record)
            if settings_of(record) != CONFIGURED:
                assert detection.peak_di is None and "settings differ" in detection.abstain_reason
        node_maps = s.scalars(select(DiMapRow).where(DiMapRow.source == MapSource.NODE)).all()
        last_boot = [m for m in node_maps if by_id[m.measurement_id].boot_id == node.boot_id]
        assert last_boot, "the node's own maps went on after its last reboot"
        for node_map in last_boot:  # against the record that refilled its baseline slot, in that boot
            assert by_id[node_map.baseline_measurement_id].boot_id == node.boot_id
        assert node.state.value in ("calibrating", "ok")

    read(url, verify)


def test_another_node_on_the_port_is_surfaced_and_nothing_is_stored_and_a_clamped_length_is_surfaced(tmp_path):
    mock, gw, url = run_fleet(tmp_path, scenario_node("node-x", 21) + scenario_node("node-c", 22),
                              ["node-x", "node-c"], [{"id": "pipe-a", "link": "node-x"}, {"id": "node-c", "n_samples": 9000}])

    def both_seen(s):
        rows = s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == "node-c")).all()
        swapped_node = s.get(NodeRow, "pipe-a")
        return len(rows) >= 3 and swapped_node is not None and swapped_node.link_problems

    try:
        wait_until(lambda: read(url, both_seen), 120, 0.5, what="the clamped node measuring, the swapped one surfaced")
    finally:
        gw.close()
        mock.close()

    def verify(s):
        swapped_node = s.get(NodeRow, "pipe-a")
        assert swapped_node.reported_node_id == "node-x"
        assert "reports 'node-x', configured 'pipe-a'" in swapped_node.link_problems[0]
        assert s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == "pipe-a")).all() == []
        clamped_node = s.get(NodeRow, "node-c")
        assert "n_samples: 9000 configured, the node takes at most 8000" in clamped_node.link_problems[0]
        assert clamped_node.applied_settings["n_samples"] == 8000
        for row in s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == "node-c")):
            assert row.n_samples == 8000 and load_traces(row).shape == (16, 8000)
        events = {(e.node_id, e.kind) for e in s.scalars(select(EventRow))}
        assert {("pipe-a", "node_misconfigured"), ("node-c", "node_misconfigured")} <= events

    read(url, verify)
    assert "answers as node 'node-x', configured as 'pipe-a'" in gw.stderr
