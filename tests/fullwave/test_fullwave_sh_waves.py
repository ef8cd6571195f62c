"""The SH model's waves against theory: ends, time of flight, temperature, thinning and masses.

Every reference value comes from theory (the wave speed sqrt(mu / rho) of the paper's steel, the
impedance of the wall, the scheme's own dispersion relation), never from the model's output.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from fullwave.defects import Mass, Notch
from fullwave.dispersion import numerical_velocities
from fullwave.transducers import averaging_weights, forcing_weights
from tests.support.fullwave_setups import (
    C_T,
    STEEL,
    WALL_M,
    envelope_peak,
    line,
    patch,
    pulse_s,
    ring_band,
    run,
    wall,
    window,
)

MM = 1e-3


def _pulse_window(path_mm: float, frequency_hz: float = 85e3) -> tuple[float, float]:
    """From a little before the pulse can arrive over ``path_mm`` to a little after it has passed."""
    start = path_mm * MM / C_T
    return start - 5e-6, start + pulse_s(frequency_hz) + 15e-6


def _best_match(pulse: np.ndarray, echo: np.ndarray, lag_steps: float, within_steps: float) -> float:
    """Largest normalised correlation of ``echo`` with ``pulse`` delayed by lag_steps +- within_steps."""
    lags = range(int(lag_steps - within_steps), int(lag_steps + within_steps) + 1)
    norm = np.linalg.norm(pulse) * np.linalg.norm(echo)
    return max(float(np.dot(np.roll(pulse, lag), echo)) / norm for lag in lags)


@pytest.mark.parametrize("frequency_hz", [75e3, 85e3])
def test_free_end_reflects_t01_with_unit_coefficient_and_unchanged_phase(frequency_hz):
    # source at 300 mm, receiver at 500 mm: direct over 200 mm, the left end's echo over 800 mm
    r = line(1200.0, 300.0, [500.0], "reflecting", frequency_hz=frequency_hz)
    x = r.out[:, 0]
    direct = window(r.t_s, x, *_pulse_window(200.0, frequency_hz))
    echo = window(r.t_s, x, *_pulse_window(800.0, frequency_hz))
    t_direct, a_direct = envelope_peak(r.t_s, direct, 0.0, 1.0)
    t_echo, a_echo = envelope_peak(r.t_s, echo, 0.0, 1.0)
    assert a_echo / a_direct == pytest.approx(1.0, abs=0.005)  # |R| = 1 (velocity, traction-free end)
    # phase: the echo is the direct pulse delayed, not inverted (R = +1 for velocity, -1 for traction):
    # the best match within a quarter period of the envelopes' delay is the pulse itself
    assert _best_match(direct, echo, (t_echo - t_direct) / r.dt_s, 0.25 / frequency_hz / r.dt_s) > 0.995


@pytest.mark.parametrize("frequency_hz", [75e3, 85e3])
def test_absorbing_end_reflects_less_than_minus_60_db(frequency_hz):
    r = line(1200.0, 300.0, [500.0], "absorbing", frequency_hz=frequency_hz)
    x = r.out[:, 0]
    _, a_direct = envelope_peak(r.t_s, window(r.t_s, x, *_pulse_window(200.0, frequency_hz)), 0.0, 1.0)
    lo, hi = _pulse_window(800.0, frequency_hz)
    a_echo = np.abs(window(r.t_s, x, lo - 20e-6, hi + 20e-6)).max()
    assert a_echo / a_direct < 1e-3


def test_time_of_flight_between_two_receivers_matches_the_shear_wave_group_velocity():
    # receivers 200 and 600 mm from the source; every echo arrives after the windows
    r = line(1400.0, 200.0, [400.0, 800.0], "reflecting", duration_s=300e-6)
    t_near, _ = envelope_peak(r.t_s, r.out[:, 0], *_pulse_window(200.0))
    t_far, _ = envelope_peak(r.t_s, r.out[:, 1], *_pulse_window(600.0))
    measured = 0.4 / (t_far - t_near)
    assert measured == pytest.approx(C_T, rel=3e-3)  # the physical T(0,1) velocity, within grid dispersion
    _, grid_group = numerical_velocities(85e3, C_T, r.grid.dz_m, r.grid.ds_m, r.dt_s)
    assert measured == pytest.approx(grid_group, rel=3e-4)  # and the scheme's own dispersion relation


def test_warming_slows_the_wave_by_the_stated_coefficient_per_degree():
    travel = []
    for temperature_c in (20.0, 35.0):
        r = line(1400.0, 200.0, [400.0, 800.0], "reflecting", duration_s=300e-6, temperature_c=temperature_c)
        t_near, _ = envelope_peak(r.t_s, r.out[:, 0], *_pulse_window(200.0))
        t_far, _ = envelope_peak(r.t_s, r.out[:, 1], *_pulse_window(600.0))
        travel.append(t_far - t_near)
    expected = 1.0 / (1.0 - 1e-4 * 15.0)  # c(T) = c(20) (1 - 1e-4 (T - 20))
    assert travel[1] / travel[0] - 1.0 == pytest.approx(expected - 1.0, rel=0.03)


def test_wall_thinning_reflects_and_transmits_as_its_impedance_step():
    # full-circumference thinning 4 -> 3 mm from 500 to 900 mm; absorbing ends keep the windows clean
    step = Notch(axial_mm=700.0, angle_deg=0.0, circumferential_mm=4.0, axial_length_mm=400.0, depth_mm=1.0)
    r = line(1200.0, 200.0, [300.0, 600.0], "absorbing", defects=[step])
    before, inside = r.out[:, 0], r.out[:, 1]
    incident = window(r.t_s, before, *_pulse_window(100.0))
    reflected = window(r.t_s, before, *_pulse_window(500.0))
    transmitted = window(r.t_s, inside, *_pulse_window(400.0))
    _, a_inc = envelope_peak(r.t_s, incident, 0.0, 1.0)
    _, a_ref = envelope_peak(r.t_s, reflected, 0.0, 1.0)
    _, a_tra = envelope_peak(r.t_s, transmitted, 0.0, 1.0)
    h1, h2 = 4.0, 3.0  # impedance rho c h: R = (h1 - h2) / (h1 + h2), T = 2 h1 / (h1 + h2) for velocity
    assert a_ref / a_inc == pytest.approx((h1 - h2) / (h1 + h2), rel=0.03)
    assert a_tra / a_inc == pytest.approx(2 * h1 / (h1 + h2), rel=0.01)
    # thinning: the echo keeps the incident polarity (R > 0)
    assert _best_match(incident, reflected, 400e-3 / C_T / r.dt_s, 0.25 / 85e3 / r.dt_s) > 0.99


STRIP_MM = 120.0  # circumference of the strip the mass tests run on


def _ring_backscatter(mass: Mass) -> float:
    """Peak of the change a mass makes at a ring-averaged receiver in front of it, over the incident peak."""
    traces = []
    for defects in ((), (mass,)):
        medium = wall(500.0, STRIP_MM, 1.0, "absorbing", defects)
        grid = medium.grid
        r = run(medium, forcing_weights(ring_band(grid, 100.0, 1.0)),
                averaging_weights([ring_band(grid, 200.0, 1.0)]), 1, 250e-6, frequency_hz=75e3)
        traces.append(r.out[:, 0])
    _, incident = envelope_peak(r.t_s, traces[0], *_pulse_window(100.0, 75e3))
    return float(np.abs(traces[1] - traces[0]).max() / incident)


def _point_mass_reflection(mass_kg: float, frequency_hz: float) -> float:
    """Born limit of a small mass M: it pushes back with M omega^2 w, a line force M omega^2 w / C that
    sends each way a wave of velocity F / (2 rho h c): |R| = omega M / (2 rho h c C)."""
    rho_h = STEEL.density_kg_m3 * WALL_M
    return 2 * math.pi * frequency_hz * mass_kg / (2 * rho_h * C_T * STRIP_MM * MM)


def test_a_light_mass_reflects_as_a_point_mass_and_a_near_rigid_one_much_more():
    light = _ring_backscatter(Mass(axial_mm=300.0, angle_deg=90.0, diameter_mm=6.0, mass_kg=0.0005))
    heavy = _ring_backscatter(Mass(axial_mm=300.0, angle_deg=90.0, diameter_mm=6.0, mass_kg=10.0))
    assert light == pytest.approx(_point_mass_reflection(0.0005, 75e3), rel=0.1)
    # 10 kg is far beyond the Born limit (|R| would be ~200): it saturates at a clamped disc's reflection
    assert 3 * light < heavy < 0.2


def test_transducer_patch_source_is_heard_only_after_the_wave_can_arrive():
    medium = wall(300.0, 60.0, 1.0, "reflecting")
    grid = medium.grid
    r = run(medium, forcing_weights(patch(grid, 50.0, 30.0)), averaging_weights([patch(grid, 250.0, 30.0)]), 1,
            150e-6)
    first = (200.0 - 15.0) * MM / C_T  # nearest edges of the two 15 mm patches
    quiet = np.abs(r.out[r.t_s < 0.97 * first, 0]).max()
    assert quiet < 1e-6 * np.abs(r.out[:, 0]).max()
    assert math.isfinite(float(np.abs(r.out).max()))
