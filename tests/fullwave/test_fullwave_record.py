"""A full-wave record: the documented measurement format, its timing and level, its errors."""
from __future__ import annotations

import ast
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import hilbert

from fullwave.defects import Mass, Notch
from fullwave.record import DIRECT_ARRIVAL_V, PipeModel, SimulationError, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.formats import load_npz, save_npz
from tests.support.fullwave_setups import C_T

SMALL = SimulationSpec(pipe=PipeModel(length_mm=300.0), rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=200.0),
                       cell_mm=2.0, n_samples=1500)


def _direct_envelope(m, lo_s, hi_s):
    t = np.arange(m.n_samples) / m.fs_hz
    inside = (t >= lo_s) & (t <= hi_s)
    env = np.abs(hilbert(np.where(inside, m.traces, 0.0), axis=1))
    return t[env.argmax(axis=1)], env.max(axis=1)


def test_record_is_a_measurement_in_the_documented_format_and_survives_a_file(tmp_path):
    m = simulate(SMALL)
    assert m.traces.shape == (16, 1500) and m.traces.dtype == np.float32
    assert m.fs_hz == 10e6 and m.t0_s == 0.0
    assert m.circumference_mm == pytest.approx(math.pi * 114.6)  # what a node reports: pi x OD
    assert m.velocity_m_s == 3130.0 and m.pipe_length_mm == 300.0 and m.tx_axial_mm == 50.0
    assert m.tx_rx_distance_mm == 200.0 and m.excitation_hz == 85e3 and m.cycles == 5
    np.testing.assert_allclose(m.rx_angles_deg, np.arange(16) * 22.5)
    loaded = load_npz(save_npz(m, tmp_path / "r.npz"))
    np.testing.assert_array_equal(loaded.traces, m.traces)
    assert (loaded.pipe_length_mm, loaded.tx_axial_mm) == (300.0, 50.0)


@pytest.mark.parametrize(("n", "frequency_hz", "level_v"), [(16, 85e3, DIRECT_ARRIVAL_V), (8, 75e3, DIRECT_ARRIVAL_V / 2)])
def test_direct_arrival_peaks_at_the_time_of_flight_with_the_rings_level(n, frequency_hz, level_v):
    spec = SimulationSpec(pipe=PipeModel(ends="absorbing"), rings=RingLayout(n_transducers=n),
                          excitation_hz=frequency_hz, n_samples=2200)
    m = simulate(spec)
    expected_s = 0.4 / C_T + 2.5 / frequency_hz  # envelope peak: half the 5-cycle burst after the arrival
    times, levels = _direct_envelope(m, 0.4 / C_T - 10e-6, expected_s + 50e-6)
    assert np.all(np.abs(times - expected_s) < 0.5e-6)  # grid dispersion delays it ~0.3 us over 400 mm
    np.testing.assert_allclose(levels, level_v, rtol=0.02)  # fewer transducers, proportionally less signal


def test_a_defect_changes_the_record_only_once_the_wave_can_have_reached_it_and_come_back():
    notch = Notch(axial_mm=100.0, angle_deg=0.0)
    spec = SMALL.with_changes(pipe=PipeModel(length_mm=300.0, ends="absorbing"), n_samples=1200)
    baseline, current = simulate(spec), simulate(spec.with_changes(defects=(notch,)))
    change = np.abs(current.traces - baseline.traces).max(axis=0)
    assert change.max() > 1e-3 * np.abs(baseline.traces).max()
    # Tx patches (15 mm long) at 0, the notch from 95 mm, the Rx patches from 192.5 mm; the first change
    # reaches the Rx ring after (95 - 7.5) mm to the notch plus (192.5 - 105) mm on to the nearest receiver
    earliest_s = ((95.0 - 7.5) + (192.5 - 105.0)) * 1e-3 / C_T
    t = np.arange(spec.n_samples) / spec.fs_hz
    assert change[t < 0.97 * earliest_s].max() < 1e-6 * change.max()


def test_the_wave_travels_the_mid_wall_circumference_unless_told_otherwise():
    assert PipeModel().wave_circumference_mm == pytest.approx(math.pi * (114.6 - 4.0))
    assert PipeModel(circumference_mm=360.0).wave_circumference_mm == 360.0


@pytest.mark.parametrize("spec", [
    SMALL.with_changes(rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=260.0)),  # Rx beyond the end
    SMALL.with_changes(defects=(Notch(axial_mm=400.0, angle_deg=0.0),)),  # outside the pipe
    SMALL.with_changes(defects=(Notch(axial_mm=100.0, angle_deg=0.0, depth_mm=4.0),)),  # through the wall
    SMALL.with_changes(defects=(Mass(axial_mm=100.0, angle_deg=0.0, mass_kg=-1.0),)),
    SMALL.with_changes(courant=1.5),
    SMALL.with_changes(model="fem"),
    SMALL.with_changes(temperature_c=1e5),
    SMALL.with_changes(rings=RingLayout(tx_axial_mm=5.0, tx_rx_distance_mm=200.0)),  # Tx patches off the end
    SMALL.with_changes(rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=200.0, n_transducers=30)),  # overlap
    SMALL.with_changes(cell_mm=-1.0),
], ids=["rx-beyond-end", "notch-outside", "notch-through-wall", "negative-mass", "unstable", "model", "temperature",
        "tx-off-the-end", "patches-overlap", "cell"])
def test_impossible_specs_are_refused_with_a_simulation_error(spec):
    with pytest.raises(SimulationError):
        simulate(spec)


def test_the_engine_shares_no_code_with_the_mock_nodes_ray_model():
    package = Path(__file__).resolve().parents[2] / "fullwave"
    imported = set()
    for path in package.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                imported.add(node.module)
            elif isinstance(node, ast.Import):
                imported.update(alias.name for alias in node.names)
    roots = {name.split(".")[0] for name in imported} - set(sys.stdlib_module_names)
    assert {"fullwave", "imaging", "numpy"} <= roots <= {"fullwave", "imaging", "numpy", "scipy", "numba"}
    assert not any(name.startswith("mocknode") for name in imported)  # nothing above imaging, no ray model
