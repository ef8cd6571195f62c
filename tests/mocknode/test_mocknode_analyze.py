"""The mock node's traces, read over a real pseudo-terminal and fed to `pipesentry analyze`, localize its defect."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from db.measurement_build import measurement_from_codes
from gateway.config import GeometryOverride
from gateway.geometry import effective_geometry
from gateway.node_client import NodeClient
from imaging.formats import save_npz
from imaging.timing import surface_distance_mm
from mocknode.scenario import DefectSpec, NodeScenario, NotchSize
from mocknode.server import MockNodeServer
from tests.support.clocks import ManualClock

pytestmark = pytest.mark.e2e  # runs the system's real processes

APPEARS_S = 1.5


def test_analyze_localizes_the_mock_nodes_notch(tmp_path):
    method, tolerance_mm = "multipath", 20.0
    notch = DefectSpec(kind="notch", axial_mm=250.0, angle_deg=135.0, size=NotchSize(), appears_at_s=APPEARS_S)
    scn = NodeScenario(node_id="pipe", seed=3, defects=[notch])
    clock = ManualClock()
    with MockNodeServer([scn], clock=clock) as server, NodeClient(server.urls["pipe"], timeout_s=2.0) as client:
        info = client.info()
        config = client.configure(85e3, 5, 10, 6000)
        view = effective_geometry(info, GeometryOverride(pipe_length_mm=scn.pipe.length_mm,
                                                          tx_axial_mm=scn.rings.tx_axial_mm))
        files = {}
        for name, as_baseline in (("baseline", True), ("current", False)):
            if not as_baseline:
                clock.advance(APPEARS_S + 0.2)  # the node's time: the notch has appeared
            acq = client.acquire(baseline=as_baseline)
            tr = client.read_traces(acq.measurement_id)
            m = measurement_from_codes(tr.codes, tr.volts_per_code, fs_hz=tr.fs_hz, t0_s=tr.t0_s, view=view,
                                       channels=tr.channels, excitation_hz=config.excitation_hz, cycles=config.cycles,
                                       temperature_c=tr.temperature_c)
            files[name] = save_npz(m, tmp_path / f"{name}.npz")
    proc = subprocess.run(
        [sys.executable, "-m", "pipesentry", "analyze", "--baseline", str(files["baseline"]),
         "--current", str(files["current"]), "--json", "--method", method, "--wall-mm", str(scn.pipe.wall_mm)],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["method"] == method and result["detected"] is True
    best = result["defects"][0]
    error = surface_distance_mm(best["axial_mm"], best["angle_deg"], notch.axial_mm, notch.angle_deg,
                                scn.pipe.outer_circumference_mm)
    assert error < tolerance_mm, (best, error)
