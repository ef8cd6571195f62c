"""The SH time-stepping kernel: its compiled loop against the numpy reference, energy, symmetry."""
from __future__ import annotations

import numpy as np
import pytest

from fullwave import sh
from fullwave.absorber import cpml
from fullwave.defects import Mass, Notch
from fullwave.dispersion import stable_dt_s
from fullwave.transducers import averaging_weights, forcing_weights, tone_burst
from tests.support.fullwave_setups import patch, wall

DEFECTS = (Notch(axial_mm=100.0, angle_deg=90.0), Mass(axial_mm=60.0, angle_deg=200.0, diameter_mm=6.0, mass_kg=10.0))


def _operator(medium, dtype):
    grid = medium.grid
    dt = stable_dt_s(grid.dz_m, grid.ds_m, medium.max_shear_velocity_m_s, 0.9)
    return sh.sh_operator(medium, dt, cpml(grid, medium.max_shear_velocity_m_s, 85e3, dt), dtype), dt


def _burst(dt, n):
    return tone_burst(np.arange(n) * dt, 85e3, 5)


def test_compiled_kernel_equals_the_numpy_reference_step_for_step(monkeypatch):
    assert sh._run_compiled is not None, "numba is a dependency: the compiled kernel must be in use"
    medium = wall(120.0, 40.0, 1.0, "absorbing", DEFECTS[:1] + (Mass(30.0, 200.0),), absorber_mm=20.0)
    op, dt = _operator(medium, np.float64)
    grid = medium.grid
    source = forcing_weights(patch(grid, 30.0, 37.5))
    receivers = averaging_weights([patch(grid, 95.0, 5.0, 10.0), patch(grid, 95.0, 25.0, 10.0)])
    compiled = sh.ShState.zeros(grid.nz, grid.ns, np.float64)
    out_compiled = sh.run(op, compiled, _burst(dt, 400), source, receivers, 2)
    monkeypatch.setattr(sh, "_run_compiled", None)
    reference = sh.ShState.zeros(grid.nz, grid.ns, np.float64)
    out_reference = sh.run(op, reference, _burst(dt, 400), source, receivers, 2)
    assert np.abs(out_reference).max() > 0
    np.testing.assert_allclose(out_compiled, out_reference, rtol=0, atol=1e-12 * np.abs(out_reference).max())
    for name in ("v", "tau_z", "tau_s", "psi_v", "psi_tau"):
        a, b = getattr(compiled, name), getattr(reference, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(np.abs(b).max(), 1e-300))


def _energies(medium, dtype, n_after, every):
    op, dt = _operator(medium, dtype)
    grid = medium.grid
    source = forcing_weights(patch(grid, 45.0, 17.5))
    receivers = averaging_weights([patch(grid, 150.0, 5.0, 10.0)])
    state = sh.ShState.zeros(grid.nz, grid.ns, dtype)
    burst_steps = int(5 / 85e3 / dt) + 2
    sh.run(op, state, _burst(dt, burst_steps), source, receivers, 1)
    energies = []
    for _ in range(n_after):
        before = state.copy()
        sh.run(op, state, np.zeros(1), source, receivers, 1)
        energies.append(sh.energy_j(op, before, state, grid.dz_m, grid.ds_m))
        sh.run(op, state, np.zeros(every), source, receivers, 1)
    return np.array(energies)


@pytest.mark.parametrize(("dtype", "tolerance"), [(np.float64, 1e-12), (np.float32, 1e-6)])
def test_energy_is_conserved_with_free_ends_and_no_damping(dtype, tolerance):
    medium = wall(200.0, 60.0, 1.0, "reflecting", DEFECTS)
    energies = _energies(medium, dtype, n_after=6, every=400)  # ~2400 steps, waves crossing defects and ends
    assert energies[0] > 0
    assert np.ptp(energies) / energies[0] < tolerance


def test_absorbing_layers_drain_the_energy():
    medium = wall(200.0, 60.0, 1.0, "absorbing", DEFECTS, absorber_mm=40.0)
    energies = _energies(medium, np.float64, n_after=6, every=400)
    assert np.all(np.diff(energies) < 0)
    assert energies[-1] < 0.01 * energies[0]


def _field(shift_deg: float):
    defects = tuple(type(d)(**{**d.__dict__, "angle_deg": (d.angle_deg + shift_deg) % 360.0}) for d in DEFECTS)
    medium = wall(160.0, 60.0, 1.0, "reflecting", defects)
    op, dt = _operator(medium, np.float64)
    grid = medium.grid
    s_mm = (30.0 + shift_deg / 360.0 * 60.0) % 60.0
    receivers = averaging_weights([patch(grid, 120.0, 5.0, 10.0)])
    state = sh.ShState.zeros(grid.nz, grid.ns, np.float64)
    sh.run(op, state, _burst(dt, 500), forcing_weights(patch(grid, 45.0, s_mm)), receivers, 1)
    return state.v


@pytest.mark.parametrize("cells", [7, 30])  # 30 cells round takes the source patch across s = 0
def test_shifting_source_and_defects_round_the_circumference_shifts_the_field(cells):
    shift_deg = 360.0 * cells / 60.0
    base, shifted = _field(0.0), _field(shift_deg)
    np.testing.assert_allclose(shifted, np.roll(base, cells, axis=1), rtol=0, atol=1e-9 * np.abs(base).max())


def test_source_and_receiver_swap_gives_the_same_trace_through_defects():
    medium = wall(160.0, 60.0, 1.0, "reflecting", DEFECTS)
    op, dt = _operator(medium, np.float64)
    grid = medium.grid
    a, b = patch(grid, 40.0, 10.0, 10.0), patch(grid, 130.0, 40.0, 10.0)
    traces = []
    for source, receiver in ((a, b), (b, a)):
        state = sh.ShState.zeros(grid.nz, grid.ns, np.float64)
        traces.append(sh.run(op, state, _burst(dt, 700), forcing_weights(source),
                             averaging_weights([receiver]), 1)[:, 0])
    assert np.abs(traces[0]).max() > 0
    np.testing.assert_allclose(traces[0], traces[1], rtol=0, atol=1e-9 * np.abs(traces[0]).max())
