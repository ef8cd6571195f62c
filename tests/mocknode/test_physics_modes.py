"""Mock-node physics of the other guided modes: dispersion, ring leakage, mode conversion at defects.

Specifications: the plate-helix dispersion meets its known limits; a leaked mode arrives at the
Rx ring after distance / group velocity with the amplitude asked for, reflects at the ends and
dies below its cut-off; a converted mode varies as cos(n theta) round the ring; leakage is the
same in baseline and current, so a defect-free record stays below the detection threshold and a
defect is still located; with no other modes the traces are exactly the T(0,1)-only model's.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.signal import hilbert
from scipy.special import jvp, yvp

from imaging.pipeline import AssessSettings, assess
from imaging.timing import surface_distance_mm
from mocknode.dispersion import (
    DispersionError,
    bulk_velocities,
    cutoff_hz,
    group_velocity_m_s,
    parse_mode,
    plate_wavenumber,
)
from mocknode.physics import (
    Acquisition,
    all_arrivals,
    defects_at,
    direct_gain_v,
    quantise_volts,
    render,
    simulate_volts,
    velocity_m_s,
)
from mocknode.scenario import (
    AcquisitionSpec,
    DefectSpec,
    ExcitationSpec,
    ModeConversion,
    ModeLeak,
    ModesSpec,
    NodeScenario,
    PipeSpec,
    RingSpec,
    ScenarioError,
    scenario_from_dict,
)

FS = 10e6
QUIET = AcquisitionSpec(noise_v_rms=0.0)
DIRECT_V = QUIET.direct_amplitude_v
GEOMETRY = dict(thickness_mm=4.0, mid_radius_mm=(114.6 - 4.0) / 2, shear_m_s=3130.0, poisson=0.3)
PULSE_CENTRE_US = 2.5 / 85e3 * 1e6


def node(modes: ModesSpec | dict | None = None, **update) -> NodeScenario:
    update.setdefault("acquisition", QUIET)
    update.setdefault("pipe", PipeSpec(ends="absorbing"))
    return NodeScenario(node_id="m", modes=modes or ModesSpec(), **update)


def volts(scn: NodeScenario, temperature_c: float = 20.0) -> np.ndarray:
    return simulate_volts(scn, elapsed_s=0.0, temperature_c=temperature_c, rng=np.random.default_rng(0),
                          include_noise=False)


def notch(axial_mm: float, angle_deg: float) -> DefectSpec:
    return DefectSpec(kind="notch", axial_mm=axial_mm, angle_deg=angle_deg)


# --- dispersion ---------------------------------------------------------------------------


def test_mode_names_parse_to_order_and_family() -> None:
    assert parse_mode("L(0,1)") == (0, 1)
    assert parse_mode("L(0,2)") == (0, 3)
    assert parse_mode("T(0,1)") == (0, 2)
    assert parse_mode("F(8,2)") == (8, 2)
    for bad in ("F(0,2)", "F(1,4)", "L(0,3)", "T(1,1)", "x"):
        with pytest.raises(DispersionError):
            parse_mode(bad)


def test_torsional_family_without_circumferential_order_is_exactly_the_shear_velocity() -> None:
    f = np.array([20e3, 85e3, 300e3])
    np.testing.assert_allclose(group_velocity_m_s(0, 2, f, **GEOMETRY), 3130.0, rtol=1e-9)


def test_s0_and_a0_meet_their_low_frequency_plate_limits() -> None:
    c_l, c_t = bulk_velocities(3130.0, 0.3)
    c_plate = c_t * math.sqrt(2 / (1 - 0.3))  # sqrt(E / (rho (1 - nu^2)))
    f = 2e3
    k_s0 = plate_wavenumber(3, np.array([f]), 4.0, 3130.0, 0.3)[0] * 1000
    assert 2 * math.pi * f / k_s0 == pytest.approx(c_plate, rel=1e-3)
    # Classical plate bending: c = sqrt(omega c_plate t / sqrt(12)).
    omega = 2 * math.pi * f
    k_a0 = plate_wavenumber(1, np.array([f]), 4.0, 3130.0, 0.3)[0] * 1000
    assert omega / k_a0 == pytest.approx(math.sqrt(omega * c_plate * 0.004 / math.sqrt(12)), rel=0.01)
    assert c_l == pytest.approx(5855.7, abs=0.5)


def test_s0_at_the_excitation_frequency_travels_near_5_3_km_per_s() -> None:
    cg = group_velocity_m_s(0, 3, np.array([75e3, 85e3]), **GEOMETRY)
    assert np.all((cg > 5200.0) & (cg < 5350.0))


@pytest.mark.parametrize("order", [1, 8, 16])
def test_torsional_family_flexural_cutoff_matches_the_exact_annulus_antiplane_mode(order: int) -> None:
    inner, outer = 114.6 / 2 - 4.0, 114.6 / 2

    def det(k):
        return jvp(order, k * inner) * yvp(order, k * outer) - jvp(order, k * outer) * yvp(order, k * inner)

    ks = np.linspace(0.5, 1.5, 400) * order / GEOMETRY["mid_radius_mm"]
    values = det(ks)
    i = int(np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))[0])
    exact_hz = brentq(det, ks[i], ks[i + 1]) * 3130e3 / (2 * math.pi)
    assert cutoff_hz(order, 2, **GEOMETRY) == pytest.approx(exact_hz, rel=1e-3)


def test_ring_order_torsional_flexural_mode_propagates_for_8_transducers_not_16() -> None:
    assert cutoff_hz(8, 2, **GEOMETRY) == pytest.approx(72.1e3, rel=0.01)  # below 75 and 85 kHz
    assert cutoff_hz(16, 2, **GEOMETRY) > 140e3
    slow = group_velocity_m_s(8, 2, np.array([75e3, 85e3]), **GEOMETRY)
    assert 0 < slow[0] < slow[1] < 2000.0  # strongly dispersive just above cut-off
    assert group_velocity_m_s(16, 2, np.array([85e3]), **GEOMETRY)[0] == 0.0


# --- scenario -----------------------------------------------------------------------------


def test_scenario_rejects_unknown_modes_and_t01_naming_the_key() -> None:
    for mode in ("Q(1,1)", "T(0,1)"):
        with pytest.raises(ScenarioError) as err:
            scenario_from_dict({"nodes": [{"node_id": "a", "modes": {"leaks": [{"mode": mode, "amplitude": 0.1}]}}]})
        assert err.value.key == "nodes.0.modes.leaks.0.mode"


# --- leakage ------------------------------------------------------------------------------


def test_without_other_modes_the_traces_are_exactly_the_t01_model() -> None:
    scn = node(defects=[notch(200.0, 90.0)], pipe=PipeSpec(ends="reflecting"))
    # Conversions only act on defects: with none present the record is also untouched.
    converting = node(ModesSpec(conversions=[ModeConversion(mode="F(1,1)", ratio=1.0)]))
    for s in (scn, node(), converting):
        v = velocity_m_s(s, 23.0)
        t01 = render(s, all_arrivals(s, defects_at(s, 0.0), v), v) * direct_gain_v(s)
        assert np.array_equal(volts(s, 23.0), t01)


def test_l02_leak_arrives_after_distance_over_group_velocity_with_its_amplitude() -> None:
    base = volts(node())
    leak = volts(node(ModesSpec(leaks=[ModeLeak(mode="L(0,2)", amplitude=0.05)])))
    diff = leak - base
    env = np.abs(hilbert(diff, axis=-1))
    cg = group_velocity_m_s(0, 3, np.array([85e3]), **GEOMETRY)[0]
    expected_us = 400.0 / (cg * 1e-3) + PULSE_CENTRE_US  # 75.9 us + 29.4 us, well before T(0,1) at 127.8 us
    peaks_us = np.argmax(env, axis=1) / FS * 1e6
    np.testing.assert_allclose(peaks_us, expected_us, atol=0.5)
    np.testing.assert_allclose(np.abs(diff).max(axis=1), 0.05 * DIRECT_V, rtol=0.03)  # same at every receiver


def test_leaked_modes_reflect_at_free_ends_like_t01() -> None:
    # Ends at -300 and 700 mm: after the direct 400 mm, the far end (1000 mm) and the near end (1000 mm).
    spec = ModesSpec(leaks=[ModeLeak(mode="L(0,2)", amplitude=0.05)])
    diff = (volts(node(spec, pipe=PipeSpec(ends="reflecting"))) - volts(node(pipe=PipeSpec(ends="reflecting"))))[0]
    env = np.abs(hilbert(diff))
    cg_mm_us = group_velocity_m_s(0, 3, np.array([85e3]), **GEOMETRY)[0] * 1e-3
    at = round((1000.0 / cg_mm_us + PULSE_CENTRE_US) * 1e-6 * FS)
    direct = env[round((400.0 / cg_mm_us + PULSE_CENTRE_US) * 1e-6 * FS)]
    assert env[at] == pytest.approx(2 * direct, rel=0.05)  # two coincident 1000 mm paths, R = 1 each


def test_ring_order_flexural_leak_dies_below_cutoff_and_reaches_the_rx_ring_above() -> None:
    leak16 = ModesSpec(leaks=[ModeLeak(mode="F(16,2)", amplitude=0.1)])
    diff16 = volts(node(leak16)) - volts(node())
    assert np.abs(diff16).max() < 1e-4 * DIRECT_V  # evanescent at 85 kHz: only the spectrum's far tail survives
    ring8 = dict(rings=RingSpec(n_transducers=8), excitation=ExcitationSpec(frequency_hz=75e3))
    leak8 = ModesSpec(leaks=[ModeLeak(mode="F(8,2)", amplitude=0.1)])
    diff8 = volts(node(leak8, **ring8)) - volts(node(**ring8))
    peak = np.abs(diff8).max(axis=1)
    assert np.all(peak > 0.01 * DIRECT_V)  # spread out by dispersion, but there
    np.testing.assert_allclose(peak, peak[0], rtol=1e-9)  # order 8 looks axisymmetric to 8 receivers
    first_us = np.flatnonzero(np.abs(diff8[0]) > 0.1 * peak[0])[0] / FS * 1e6
    fastest = group_velocity_m_s(8, 2, np.linspace(60e3, 200e3, 141), **GEOMETRY).max() * 1e-3
    assert first_us > 400.0 / fastest - 5.0  # nothing outruns the mode's fastest band component


def test_a_warmer_pipe_delays_a_leak_by_the_same_fraction_as_t01() -> None:
    # c_L / c_T depends on Poisson's ratio only, so every mode slows by T(0,1)'s 1e-4 per degC.
    spec = ModesSpec(leaks=[ModeLeak(mode="L(0,2)", amplitude=0.05)])
    cold = (volts(node(spec), 20.0) - volts(node(), 20.0))[0]
    warm = (volts(node(spec), 50.0) - volts(node(), 50.0))[0]
    xc = np.correlate(warm, cold, "full")
    k = int(np.argmax(xc))
    lag = k + 0.5 * (xc[k - 1] - xc[k + 1]) / (xc[k - 1] - 2 * xc[k] + xc[k + 1]) - (cold.size - 1)
    expected_us = 30 * 1e-4 * 400.0 / 5.28 / (1 - 30 * 1e-4)  # 0.23 us: 0.3 % of the 76 us path
    assert lag / FS * 1e6 == pytest.approx(expected_us, abs=0.02)


# --- mode conversion ----------------------------------------------------------------------


@pytest.mark.parametrize("mode,order", [("F(1,1)", 1), ("F(2,3)", 2)])
def test_converted_scatter_varies_as_cos_n_theta_round_the_ring(mode: str, order: int) -> None:
    defect = [notch(150.0, 90.0)]
    spec = ModesSpec(conversions=[ModeConversion(mode=mode, ratio=1.0)])
    diff = volts(node(spec, defects=defect)) - volts(node(defects=defect))
    reference = diff[4]  # the receiver at 90 deg, behind the notch: cos(0) = 1
    gains = diff @ reference / (reference @ reference)
    theta = np.radians(np.arange(16) * 22.5)
    np.testing.assert_allclose(gains, np.cos(order * (theta - math.pi / 2)), atol=1e-9)
    lam, circ = 3130e3 / 85e3, math.pi * (114.6 - 4.0)
    ring_reflection = defects_at(node(defects=defect), 0.0)[0].strength * lam / circ
    assert np.abs(reference).max() == pytest.approx(ring_reflection * DIRECT_V, rel=0.5)  # ratio 1 x |R_T|, dispersed


def test_conversion_grows_with_the_defect_and_is_absent_before_it_appears() -> None:
    spec = ModesSpec(conversions=[ModeConversion(mode="L(0,1)", ratio=1.0)])
    later = [DefectSpec(kind="notch", axial_mm=150.0, angle_deg=90.0, appears_at_s=10.0)]
    before = simulate_volts(node(spec, defects=later), elapsed_s=5.0, temperature_c=20.0,
                            rng=np.random.default_rng(0), include_noise=False)
    assert np.array_equal(before, volts(node()))


# --- imaging on leaky records -------------------------------------------------------------

RING8_LEAKS = [ModeLeak(mode="L(0,1)", amplitude=0.05), ModeLeak(mode="L(0,2)", amplitude=0.03),
               ModeLeak(mode="F(8,1)", amplitude=0.05), ModeLeak(mode="F(8,2)", amplitude=0.10),
               ModeLeak(mode="F(1,2)", amplitude=0.02, angle_deg=40.0)]
CONVERSIONS = [ModeConversion(mode="F(1,1)", ratio=0.5), ModeConversion(mode="F(1,3)", ratio=0.3, phase_deg=90.0)]


def leaky_record(defects, temperature_c: float, seed: int, ends: str = "reflecting", convert: bool = True):
    scn = NodeScenario(node_id="leaky", pipe=PipeSpec(ends=ends, wall_mm=4.0), rings=RingSpec(n_transducers=8),
                       excitation=ExcitationSpec(frequency_hz=75e3), defects=defects,
                       modes=ModesSpec(leaks=RING8_LEAKS, conversions=CONVERSIONS if convert else []))
    v = simulate_volts(scn, elapsed_s=0.0, temperature_c=temperature_c, rng=np.random.default_rng(seed))
    codes, vpc = quantise_volts(v, scn.acquisition.adc_bits, scn.acquisition.adc_full_scale_v)
    return Acquisition(codes, vpc, scn.acquisition.fs_hz, scn.acquisition.t0_s, temperature_c, 0.0).to_measurement(scn)


def test_leakage_is_baseline_stable_so_defect_free_records_stay_below_threshold() -> None:
    baseline = leaky_record([], 20.0, seed=1)
    settings = AssessSettings(wall_mm=4.0, max_defects=1)
    for seed, temperature in ((2, 20.0), (3, 22.5), (4, 17.5)):
        result = assess(leaky_record([], temperature, seed=seed), [baseline], settings)
        assert result.valid_baseline and not result.detected
        assert result.peak_di < 0.5 * settings.effective_threshold  # measured <= 0.017 over 1000 (docs/accuracy.md)


# Bound: docs/accuracy.md "Other guided modes" measured worst 20.1 mm over 90 positions
# (leakage and conversion, +-3 degC, compensated); 30 mm leaves a margin.
@pytest.mark.parametrize("ends,axial_mm", [("reflecting", 200.0), ("absorbing", 300.0)])
def test_mass_is_located_within_30_mm_through_leakage_conversion_and_3c_drift(ends: str, axial_mm: float) -> None:
    mass = [DefectSpec(kind="mass", axial_mm=axial_mm, angle_deg=90.0)]
    baseline = leaky_record([], 20.0, seed=5, ends=ends)
    result = assess(leaky_record(mass, 23.0, seed=6, ends=ends), [baseline], AssessSettings(wall_mm=4.0))
    assert result.detected
    best = min(surface_distance_mm(d.axial_mm, d.angle_deg, axial_mm, 90.0, 360.0) for d in result.defects)
    assert best <= 30.0
