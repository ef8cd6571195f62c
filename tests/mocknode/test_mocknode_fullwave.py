"""A mock node replaying full-wave records (scenario ``fullwave``), over a real pseudo-terminal."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from db.measurement_build import measurement_from_codes
from fullwave.cases import own_cases
from fullwave.cli import generate
from gateway.config import GeometryOverride
from gateway.geometry import effective_geometry
from gateway.node_client import NodeClient
from gateway.node_errors import NodeError
from imaging.formats import load_measurement
from imaging.pipeline import AssessSettings, assess
from imaging.timing import surface_distance_mm
from mocknode.node import MockNode, NodeSetupError
from mocknode.scenario import load_scenario, scenario_from_dict
from mocknode.server import MockNodeServer
from tests.support.clocks import ManualClock

ROOT = Path(__file__).resolve().parents[2]
CASE = "fw_n16_reflecting_notch_200_250"  # the case the documented scenario names
APPEARS_S = 1.0


def _documented_scenario() -> str:
    text = (ROOT / "docs" / "simulator.md").read_text()
    section = text[text.index("## Full-wave records"):]
    return re.search(r"```toml\n(.*?)```", section, re.DOTALL).group(1)


@pytest.fixture(scope="module")
def records(tmp_path_factory) -> Path:
    """The documented case's records (on a 1 mm grid, to be quick) in out/fullwave-cases under a folder."""
    root = tmp_path_factory.mktemp("fullwave")
    case = next(c for c in own_cases() if c.name == CASE).with_cell(1.0)
    generate(root / "out" / "fullwave-cases", [case], root / "cache", log=None)
    return root


def _scenario_file(root: Path, appears_s: float) -> Path:
    text = re.sub(r"defect_appears_at_s = [0-9.]+", f"defect_appears_at_s = {appears_s}", _documented_scenario())
    path = root / "scenario.toml"
    path.write_text(text)
    return path


def test_the_documented_scenario_names_records_relative_to_its_own_folder(tmp_path):
    path = tmp_path / "site" / "scenario.toml"
    path.parent.mkdir()
    path.write_text(_documented_scenario())
    spec = load_scenario(path).nodes[0].fullwave
    assert spec is not None and spec.defect_appears_at_s == tomllib.loads(_documented_scenario())["nodes"][0][
        "fullwave"]["defect_appears_at_s"]
    assert spec.baseline == tmp_path / "site" / "out" / "fullwave-cases" / f"{CASE}_baseline.npz"


def test_records_of_another_node_are_refused_naming_what_differs(records):
    scenario = load_scenario(_scenario_file(records, APPEARS_S)).nodes[0]
    eight = scenario.model_copy(update={"rings": scenario.rings.model_copy(update={"n_transducers": 8})})
    with pytest.raises(NodeSetupError, match="receivers, transmitters"):
        MockNode(eight)
    missing = scenario_from_dict({"nodes": [{"node_id": "x", "fullwave": {"baseline": str(records / "no.npz"),
                                                                         "current": str(records / "no.npz")}}]})
    with pytest.raises(NodeSetupError, match="no such file"):
        MockNode(missing.nodes[0])


@pytest.mark.e2e
def test_a_node_replays_the_baseline_then_the_defect_and_the_imaging_finds_it(records):
    scenario = load_scenario(_scenario_file(records, APPEARS_S)).nodes[0]
    truth = own_cases()[[c.name for c in own_cases()].index(CASE)].defects[0]
    expected = load_measurement(scenario.fullwave.baseline)
    clock = ManualClock()
    with MockNodeServer([scenario], clock=clock) as server, \
            NodeClient(server.urls["fw-notch"], timeout_s=2.0) as client:
        info = client.info()
        assert info.max_samples == expected.n_samples
        with pytest.raises(NodeError, match="85000 Hz"):
            client.configure(75e3, 5, 10, 6000)  # a record cannot be replayed at another frequency
        config = client.configure(85e3, 5, 10, 6000)
        view = effective_geometry(info, GeometryOverride(pipe_length_mm=scenario.pipe.length_mm,
                                                          tx_axial_mm=scenario.rings.tx_axial_mm))
        pair = []
        for as_baseline in (True, False):
            if not as_baseline:
                clock.advance(APPEARS_S + 0.2)  # the node's time: the current record takes over
            acq = client.acquire(baseline=as_baseline)
            tr = client.read_traces(acq.measurement_id)
            pair.append(measurement_from_codes(tr.codes, tr.volts_per_code, fs_hz=tr.fs_hz, t0_s=tr.t0_s, view=view,
                                               channels=tr.channels, excitation_hz=config.excitation_hz,
                                               cycles=config.cycles, temperature_c=tr.temperature_c))
    baseline, current = pair
    a, b = baseline.traces.astype(np.float64), expected.traces.astype(np.float64)
    assert np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)) > 0.999  # the record, with the node's noise and ADC
    result = assess(current, [baseline], AssessSettings(wall_mm=scenario.pipe.wall_mm))
    assert result.detected
    error = min(surface_distance_mm(d.axial_mm, d.angle_deg, truth.axial_mm, truth.angle_deg, current.circumference_mm)
                for d in result.defects)
    assert error < 20.0
