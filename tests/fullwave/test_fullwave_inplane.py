"""The in-plane model: its kernel, its two wave speeds, ends, excitation by tilted patches and mode
conversion at a notch, against plane-stress theory (c_T = sqrt(mu / rho), c_P = sqrt(E / (rho (1 - nu^2))))."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fullwave import inplane
from fullwave.defects import Mass, Notch
from fullwave.dispersion import numerical_velocities
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from tests.support.fullwave_setups import (
    C_T,
    STEEL,
    band,
    box,
    envelope_peak,
    inplane_run,
    inplane_transducers,
    pulse_s,
    wall,
    window,
)

C_P = STEEL.plate_velocity_m_s
MM = 1e-3
DEFECTS = (Notch(axial_mm=100.0, angle_deg=90.0), Mass(axial_mm=60.0, angle_deg=200.0))


def _line(length_mm, source_mm, receivers_mm, *, axial: bool, ends="reflecting", defects=(), duration_s=400e-6,
          sense_axial: bool | None = None):
    """Plane waves along the pipe from a 1-cell band (axial or circumferential traction), sensed by
    1-cell bands along the same axis (or ``sense_axial``)."""
    medium = wall(length_mm, 4.0, 1.0, ends, defects)
    grid = medium.grid
    sense_axial = axial if sense_axial is None else sense_axial
    source_z = band(grid, source_mm, 1.0, on_faces=True) if axial else None
    source_s = None if axial else band(grid, source_mm, 1.0, s_offset=0.5)
    receivers = [(band(grid, z, 1.0, on_faces=True), None) if sense_axial else (None, band(grid, z, 1.0, s_offset=0.5))
                 for z in receivers_mm]
    return inplane_run(medium, inplane_transducers(grid, source_z, source_s, receivers), duration_s)


def _window(path_mm: float, velocity: float) -> tuple[float, float]:
    start = path_mm * MM / velocity
    return start - 5e-6, start + pulse_s() + 15e-6


def test_compiled_kernel_equals_the_numpy_reference_step_for_step(monkeypatch):
    assert inplane._run_compiled is not None, "numba is a dependency: the compiled kernel must be in use"
    medium = wall(120.0, 40.0, 1.0, "absorbing", (Notch(60.0, 90.0), Mass(30.0, 200.0)), absorber_mm=20.0)
    grid = medium.grid
    tilt = (math.sin(0.2), math.cos(0.2))
    t = inplane_transducers(grid, tilt[0] * box(grid, 30.0, 37.5, 15.0, on_faces=True),
                            tilt[1] * box(grid, 30.0, 37.5, 15.0, s_offset=0.5),
                            [(box(grid, 95.0, 5.0, 10.0, on_faces=True), box(grid, 95.0, 5.0, 10.0, s_offset=0.5)),
                             (None, box(grid, 95.0, 25.0, 10.0, s_offset=0.5))])
    compiled = inplane_run(medium, t, 80e-6)
    monkeypatch.setattr(inplane, "_run_compiled", None)
    reference = inplane_run(medium, t, 80e-6)
    scale = np.abs(reference.out).max()
    assert scale > 0
    np.testing.assert_allclose(compiled.out, reference.out, rtol=0, atol=1e-12 * scale)
    for name in ("vz", "vs", "nzz", "nss", "nzs", "psi_vz", "psi_vs", "psi_n", "psi_zs"):
        a, b = getattr(compiled.state, name), getattr(reference.state, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(np.abs(b).max(), 1e-300))


def _energies(ends):
    medium = wall(200.0, 60.0, 1.0, ends, DEFECTS, absorber_mm=40.0)
    grid = medium.grid
    t = inplane_transducers(grid, 0.3 * box(grid, 45.0, 17.5, 15.0, on_faces=True),
                            box(grid, 45.0, 17.5, 15.0, s_offset=0.5), [(None, box(grid, 150.0, 5.0, 10.0, s_offset=0.5))])
    r = inplane_run(medium, t, 62e-6)
    energies = []
    for _ in range(6):
        before = r.state.copy()
        inplane.run(r.op, r.state, np.zeros(1), t)
        energies.append(inplane.energy_j(r.op, before, r.state, grid.dz_m, grid.ds_m))
        inplane.run(r.op, r.state, np.zeros(600), t)
    return np.array(energies)


def test_energy_is_conserved_with_free_ends_and_drains_into_absorbing_ones():
    free = _energies("reflecting")
    assert free[0] > 0 and np.ptp(free) / free[0] < 1e-12
    absorbed = _energies("absorbing")
    assert np.all(np.diff(absorbed) < 0) and absorbed[-1] < 0.05 * absorbed[0]


@pytest.mark.parametrize(("axial", "velocity"), [(True, C_P), (False, C_T)], ids=["S0", "SH0"])
def test_both_waves_travel_at_their_plane_stress_velocities(axial, velocity):
    r = _line(1800.0, 200.0, [400.0, 800.0], axial=axial, duration_s=300e-6)
    t_near, _ = envelope_peak(r.t_s, r.out[:, 0], *_window(200.0, velocity))
    t_far, _ = envelope_peak(r.t_s, r.out[:, 1], *_window(600.0, velocity))
    measured = 0.4 / (t_far - t_near)
    # within the grid's dispersion: 1 mm cells, and for SH0 a time step set by the faster S0 (-0.31 %)
    assert measured == pytest.approx(velocity, rel=4e-3)
    _, grid_group = numerical_velocities(85e3, velocity, r.grid.dz_m, r.grid.ds_m, r.dt_s)
    assert measured == pytest.approx(grid_group, rel=3e-4)


@pytest.mark.parametrize("axial", [True, False], ids=["S0", "SH0"])
def test_free_end_reflects_each_wave_with_unit_coefficient_and_no_conversion(axial):
    velocity = C_P if axial else C_T
    r = _line(1200.0, 300.0, [500.0], axial=axial, duration_s=(800.0 * MM / velocity + 90e-6))
    _, direct = envelope_peak(r.t_s, r.out[:, 0], *_window(200.0, velocity))
    _, echo = envelope_peak(r.t_s, r.out[:, 0], *_window(800.0, velocity))
    assert echo / direct == pytest.approx(1.0, abs=0.005)
    other = _line(1200.0, 300.0, [500.0], axial=axial, sense_axial=not axial, duration_s=r.t_s[-1])
    assert np.abs(other.out).max() < 1e-9 * direct  # a plane wave meets the end square on: nothing converts


@pytest.mark.parametrize("axial", [True, False], ids=["S0", "SH0"])
def test_absorbing_end_reflects_each_wave_less_than_minus_60_db(axial):
    velocity = C_P if axial else C_T
    r = _line(1200.0, 300.0, [500.0], axial=axial, ends="absorbing", duration_s=(800.0 * MM / velocity + 110e-6))
    _, direct = envelope_peak(r.t_s, r.out[:, 0], *_window(200.0, velocity))
    lo, hi = _window(800.0, velocity)
    assert np.abs(window(r.t_s, r.out[:, 0], lo - 20e-6, hi + 20e-6)).max() < 1e-3 * direct


def test_a_tilted_ring_launches_longitudinal_and_torsional_waves_in_the_ratio_of_their_impedances():
    # a line force F at angle a from the circumference: v_s = F cos a / (2 rho h c_T), v_z = F sin a / (2 rho h c_P)
    tilt = math.radians(10.0)
    medium = wall(1400.0, 4.0, 1.0, "absorbing")
    grid = medium.grid
    t = inplane_transducers(grid, math.sin(tilt) * band(grid, 300.0, 1.0, on_faces=True),
                            math.cos(tilt) * band(grid, 300.0, 1.0, s_offset=0.5),
                            [(band(grid, 700.0, 1.0, on_faces=True), None), (None, band(grid, 700.0, 1.0, s_offset=0.5))])
    r = inplane_run(medium, t, 240e-6)
    _, longitudinal = envelope_peak(r.t_s, r.out[:, 0], *_window(400.0, C_P))
    _, torsional = envelope_peak(r.t_s, r.out[:, 1], *_window(400.0, C_T))
    assert longitudinal / torsional == pytest.approx(math.tan(tilt) * C_T / C_P, rel=0.02)


STRIP_MM = 80.0


def _converted(defects, sensing_axial: bool):
    """A T(0,1) plane wave from a ring at 100 mm, sensed by a 10 mm patch at 500 mm, 20 mm round from the
    line through a defect at 300 mm (on that line the field's mirror symmetry forbids axial motion)."""
    medium = wall(700.0, STRIP_MM, 1.0, "absorbing", defects)
    grid = medium.grid
    patch = (box(grid, 500.0, 60.0, 10.0, on_faces=True), None) if sensing_axial else \
        (None, box(grid, 500.0, 60.0, 10.0, s_offset=0.5))
    r = inplane_run(medium, inplane_transducers(grid, None, band(grid, 100.0, 1.0, s_offset=0.5), [patch]), 200e-6)
    return r.t_s, r.out[:, 0]


def test_a_local_notch_converts_torsion_into_the_faster_longitudinal_wave():
    local = Notch(axial_mm=300.0, angle_deg=180.0, circumferential_mm=20.0, axial_length_mm=10.0, depth_mm=2.0)
    ring = Notch(axial_mm=300.0, angle_deg=180.0, circumferential_mm=STRIP_MM, axial_length_mm=10.0, depth_mm=2.0)
    # incident torsion reaches the notch (s = 40 mm) after 200 mm at c_T; converted S0 covers the last
    # ~201 mm at c_P, arriving well before anything torsional can (400 mm at c_T = 128 us)
    lo, hi = 200.0 * MM / C_T + 200.0 * MM / C_P - 5e-6, 400.0 * MM / C_T - 3e-6
    t, incident = _converted((), sensing_axial=False)
    reference = np.abs(incident).max()
    t, converted = _converted((local,), sensing_axial=True)
    _, plain = _converted((), sensing_axial=True)
    _, symmetric = _converted((ring,), sensing_axial=True)
    early = (t >= lo) & (t <= hi)
    assert np.abs(converted[early]).max() > 1e-3 * reference
    assert np.abs(plain).max() < 1e-9 * reference  # no defect: a torsional wave stays torsional
    assert np.abs(symmetric).max() < 1e-9 * reference  # an axisymmetric thinning cannot convert by symmetry


def test_without_defects_or_tilt_the_record_is_the_sh_models_torsion():
    spec = SimulationSpec(pipe=PipeModel(length_mm=300.0, ends="absorbing"),
                          rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=200.0), cell_mm=1.0, n_samples=1300)
    sh_record, inplane_record = simulate(spec), simulate(spec.with_changes(model="inplane"))
    a, b = sh_record.traces.astype(np.float64), inplane_record.traces.astype(np.float64)
    assert np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)) > 0.999
