"""Scenario files: what loads, what is rejected, and with which key named."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from mocknode.scenario import (
    MassSize,
    NotchSize,
    ScenarioError,
    default_scenario,
    load_scenario,
    scenario_from_dict,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "scenarios"


@pytest.mark.parametrize("name", ["demo.toml", "paper_notch.toml", "paper_mass.toml", "quiet_drift.toml"])
def test_shipped_example_exists(name: str) -> None:
    assert (EXAMPLES / name).is_file()


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.name)
def test_every_example_scenario_loads(path: Path) -> None:
    scenario = load_scenario(path)
    assert scenario.nodes


def test_paper_notch_example_matches_the_paper_fe_case() -> None:
    node = load_scenario(EXAMPLES / "paper_notch.toml").nodes[0]
    assert node.rings.n_transducers == 16 and len(node.rings.rx_angles) == 16
    assert node.excitation.frequency_hz == 85e3 and node.excitation.cycles == 5
    (notch,) = node.defects
    assert (notch.kind, notch.angle_deg, notch.axial_mm) == ("notch", 90.0, 200.0)
    assert notch.size == NotchSize(circumferential_mm=20, axial_mm_len=10, depth_mm=2)


def test_paper_mass_example_is_8_transducers_75khz_10kg() -> None:
    node = load_scenario(EXAMPLES / "paper_mass.toml").nodes[0]
    assert node.rings.n_transducers == 8
    assert node.excitation.frequency_hz == 75e3
    (mass,) = node.defects
    assert mass.kind == "mass" and mass.size == MassSize(diameter_mm=6, mass_kg=10)


def test_demo_file_is_the_default_scenario() -> None:
    assert load_scenario(EXAMPLES / "demo.toml").nodes == default_scenario(3).nodes


def test_default_scenario_starts_clean_and_one_node_gets_a_notch_later() -> None:
    scenario = default_scenario(4)
    assert len({n.node_id for n in scenario.nodes}) == 4
    with_defects = [n for n in scenario.nodes if n.defects]
    assert len(with_defects) == 1
    assert all(d.appears_at_s > 0 for d in with_defects[0].defects)


def test_default_scenario_rejects_zero_nodes() -> None:
    with pytest.raises(ScenarioError):
        default_scenario(0)


def test_defaults_apply_to_every_node_and_nodes_override_them() -> None:
    scenario = scenario_from_dict(
        {
            "defaults": {"pipe": {"ends": "absorbing", "wall_mm": 5.0}},
            "nodes": [{"node_id": "a"}, {"node_id": "b", "pipe": {"wall_mm": 3.0}}],
        }
    )
    a, b = scenario.nodes
    assert a.pipe.ends == b.pipe.ends == "absorbing"
    assert (a.pipe.wall_mm, b.pipe.wall_mm) == (5.0, 3.0)


@pytest.mark.parametrize(
    ("doc", "key"),
    [
        ({"nodes": [{"node_id": "a", "rings": {"n_transducer": 8}}]}, "nodes.0.rings.n_transducer"),
        ({"nodes": [{"node_id": "a", "pipe": {"ends": "open"}}]}, "nodes.0.pipe.ends"),
        ({"nodes": [{"node_id": "a", "acquisition": {"fs_hz": -1}}]}, "nodes.0.acquisition.fs_hz"),
        (
            {"nodes": [{"node_id": "a", "defects": [{"kind": "mass", "axial_mm": 1, "angle_deg": 0,
                                                       "size": {"mass_kgs": 3}}]}]},
            "nodes.0.defects.0.size.mass_kgs",
        ),
        ({"nodes": [{"node_id": "a", "defects": [{"kind": "crack", "axial_mm": 1, "angle_deg": 0}]}]},
         "nodes.0.defects.0.kind"),
        ({"nodes": [{"node_id": "a", "faults": {"drop_byte_rate": 2}}]}, "nodes.0.faults.drop_byte_rate"),
        ({"nodes": []}, "nodes"),
    ],
)
def test_bad_input_names_the_offending_key(doc: dict, key: str) -> None:
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(doc)
    assert info.value.key == key


def test_rx_ring_beyond_the_pipe_end_is_rejected() -> None:
    with pytest.raises(ScenarioError, match="Rx ring"):
        scenario_from_dict({"nodes": [{"node_id": "a", "rings": {"tx_axial_mm": 700.0}}]})


def test_defect_outside_the_pipe_is_rejected() -> None:
    doc = {"nodes": [{"node_id": "a", "defects": [{"kind": "notch", "axial_mm": 900.0, "angle_deg": 0}]}]}
    with pytest.raises(ScenarioError, match="outside the pipe"):
        scenario_from_dict(doc)


def test_explicit_angles_must_match_the_transducer_count() -> None:
    with pytest.raises(ScenarioError, match="n_transducers"):
        scenario_from_dict({"nodes": [{"node_id": "a", "rings": {"n_transducers": 8, "rx_angles_deg": [0.0, 90.0]}}]})


def test_notch_size_on_a_mass_is_rejected() -> None:
    doc = {"nodes": [{"node_id": "a", "defects": [{"kind": "mass", "axial_mm": 1, "angle_deg": 0,
                                                   "size": {"depth_mm": 1.0}}]}]}
    with pytest.raises(ScenarioError, match="mass takes"):
        scenario_from_dict(doc)


def test_duplicate_node_ids_are_rejected() -> None:
    with pytest.raises(ScenarioError, match="duplicate node_id"):
        scenario_from_dict({"nodes": [{"node_id": "a"}, {"node_id": "a"}]})


def test_unreadable_and_malformed_files_raise_scenario_error(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[[nodes]\nnode_id = 'a'\n")
    with pytest.raises(ScenarioError, match="invalid TOML"):
        load_scenario(bad)


def test_yaml_scenarios_load_when_pyyaml_is_installed(tmp_path: Path) -> None:
    pytest.importorskip("yaml")
    path = tmp_path / "one.yaml"
    path.write_text("nodes:\n  - node_id: y\n    rings: {n_transducers: 8}\n")
    assert load_scenario(path).nodes[0].rings.n_transducers == 8


def test_the_simulator_documents_a_valid_scenario_of_its_firmware_power_up_and_fault_keys():
    text = (Path(__file__).resolve().parents[2] / "docs" / "simulator.md").read_text()
    block = next(b for b in re.findall(r"```toml\n(.*?)```", text, re.DOTALL) if "[nodes.power_up]" in b)
    node = scenario_from_dict(tomllib.loads(block)).nodes[0]
    assert node.firmware.busy_while_acquiring and node.power_up.averaging == 1
    assert [v.value for v in node.faults.violations] == ["cached_crc_stale"]
