"""A heavy mass on the wall scatters as the exact clamped disc: the engine against an analytic solution.

A mass of 1 kg on a 12-30 mm disc is 45-280x the 4 mm wall's areal mass, so the wall under it hardly
moves: a clamped disc. Its scattered field has an exact partial-wave series (imaging/scatterers.py),
which shares nothing with the engine. Its phase across the ring advances as b (1 - cos psi), which
on direct paths reads as the disc lying b / k nearer the Tx ring (docs/accuracy.md).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fullwave.defects import Mass
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.scattering import lag_on_one_minus_cos, leg0_phases
from fullwave.transducers import RingLayout
from imaging.scatterers import clamped_disc_pattern

CELL_MM = 1.0  # 10-30 cells across the discs; 2 mm cells rasterize them visibly larger
AT_MM, AT_DEG = 200.0, 100.0
ENGINE_VS_SERIES_RAD = 0.2  # measured 0.04-0.11 rad at 1 mm cells; the discs' b differ by 0.6-1.1 rad


@pytest.fixture(scope="module")
def pipe_16_absorbing():
    circumference = math.pi * PipeModel().outer_diameter_mm  # the record's: the paths below are exact
    spec = SimulationSpec(pipe=PipeModel(ends="absorbing", circumference_mm=circumference),
                          rings=RingLayout(n_transducers=16), excitation_hz=85e3, cell_mm=CELL_MM)
    return spec, simulate(spec)


@pytest.mark.parametrize("diameter_mm", [12.0, 20.0, 30.0])
def test_a_heavy_mass_on_the_engine_scatters_across_the_ring_as_the_exact_clamped_disc(pipe_16_absorbing, diameter_mm):
    spec, baseline = pipe_16_absorbing
    velocity = spec.pipe.steel.shear_velocity_m_s
    k = 2 * math.pi * spec.excitation_hz / (velocity * 1e3)
    mass = Mass(axial_mm=AT_MM, angle_deg=AT_DEG, diameter_mm=diameter_mm, mass_kg=1.0)
    current = simulate(dataclasses.replace(spec, defects=(mass,)))
    x, lag, amplitude = leg0_phases(baseline, current, AT_MM, AT_DEG, velocity)
    weight = amplitude / amplitude.max()
    measured = lag_on_one_minus_cos(x, lag, weight)
    f = clamped_disc_pattern(k * diameter_mm / 2, np.arccos(1.0 - x))
    exact = lag_on_one_minus_cos(x, np.angle(f * np.conj(f[int(np.argmin(x))])), weight)
    assert measured == pytest.approx(exact, abs=ENGINE_VS_SERIES_RAD)
