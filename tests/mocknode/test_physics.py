"""Mock-node physics: arrival times, amplitudes, temperature, noise, ADC, decimation, determinism."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import hilbert

from mocknode.paths import image_points, scattered_arrivals
from mocknode.physics import (
    PhysicsError,
    acquire,
    decimate_codes,
    defects_at,
    quantise_volts,
    simulate_volts,
    temperature_at,
)
from mocknode.scattering import ActiveDefect, notch_ring_reflection, wavelength_mm
from mocknode.scenario import (
    AcquisitionSpec,
    DefectSpec,
    ExcitationSpec,
    GrowthSpec,
    NodeScenario,
    PipeSpec,
    RingSpec,
    TemperatureSpec,
)

C_MM_PER_US = 3.130
FS = 10e6
PULSE_CENTRE_US = 2.5 / 85e3 * 1e6  # envelope peak of a 5-cycle pulse, after its start
QUIET = AcquisitionSpec(noise_v_rms=0.0, direct_amplitude_v=0.1, adc_full_scale_v=0.5)
NO_ENDS = PipeSpec(end_reflection=0.0)


def node(**update) -> NodeScenario:
    update.setdefault("acquisition", QUIET)
    return NodeScenario(node_id="t", **update)


def volts(scn: NodeScenario, temperature_c: float = 20.0, elapsed_s: float = 0.0, seed: int = 0,
          noise: bool = False) -> np.ndarray:
    return simulate_volts(scn, elapsed_s=elapsed_s, temperature_c=temperature_c,
                          rng=np.random.default_rng(seed), include_noise=noise)


def envelope(x: np.ndarray) -> np.ndarray:
    return np.abs(hilbert(x, axis=-1))


def sample_at_us(t_us: float) -> int:
    return round(t_us * 1e-6 * FS)


def envelope_peak_us(env: np.ndarray, around_us: float, half_width_us: float = 15.0) -> float:
    lo, hi = sample_at_us(around_us - half_width_us), sample_at_us(around_us + half_width_us)
    return (lo + int(np.argmax(env[lo:hi]))) / FS * 1e6


def notch(axial_mm: float, angle_deg: float, **kw) -> DefectSpec:
    return DefectSpec(kind="notch", axial_mm=axial_mm, angle_deg=angle_deg, size={}, **kw)


def test_direct_arrival_peaks_at_l_over_c_at_every_receiver() -> None:
    v = volts(node(pipe=NO_ENDS))
    expected_us = 400.0 / C_MM_PER_US + PULSE_CENTRE_US
    env = envelope(v)
    peaks_us = np.argmax(env, axis=1) / FS * 1e6
    np.testing.assert_allclose(peaks_us, expected_us, atol=0.3)
    np.testing.assert_allclose(np.abs(v).max(axis=1), 0.1, rtol=1e-3)  # direct_amplitude_v


def test_end_reflections_arrive_at_image_method_times_and_vanish_when_absorbing() -> None:
    # Ends at z=-200 and z=800; Rx at z=400: direct 400, rear end 200+600, far end 800+400,
    # rear then far 200+1000+400 mm.
    rings = RingSpec(tx_axial_mm=200.0)
    reflecting = envelope(volts(node(rings=rings)))[0]
    absorbing = envelope(volts(node(rings=rings, pipe=PipeSpec(ends="absorbing"))))[0]
    direct = reflecting.max()
    for path_mm in (800.0, 1200.0, 1600.0):
        centre_us = path_mm / C_MM_PER_US + PULSE_CENTRE_US
        assert envelope_peak_us(reflecting, centre_us) == pytest.approx(centre_us, abs=0.3)
        assert reflecting[sample_at_us(centre_us)] == pytest.approx(direct, rel=0.02)
        assert absorbing[sample_at_us(centre_us)] < 0.02 * direct


def test_image_points_count_reflections_at_both_ends() -> None:
    pos, amp = image_points(0.0, -200.0, 800.0, 0.5, max_distance_mm=1700.0, from_mm=400.0)
    found = dict(zip(np.round(np.abs(400.0 - pos), 6), amp, strict=True))
    assert found == {400.0: 1.0, 800.0: 0.5, 1200.0: 0.5, 1600.0: 0.25}


def test_defect_echo_arrives_by_the_short_and_the_long_way_round() -> None:
    # Notch 100 mm before the Rx ring at 0 deg, receiver 4 at 90 deg. A 2-cycle pulse keeps the
    # short way (C/4 round), the long way (3C/4) and the once-more way (5C/4) apart in time.
    # Absorbing ends: the only scattered paths start from the direct wave, 300 mm + r.
    scn = node(pipe=NO_ENDS, excitation=ExcitationSpec(cycles=2), defects=[notch(300.0, 0.0)])
    diff = volts(scn) - volts(scn.model_copy(update={"defects": []}))
    env = envelope(diff[4])
    quarter = scn.pipe.propagation_circumference_mm / 4
    centre_after_start_us = 1.0 / 85e3 * 1e6
    for arc_mm in (quarter, 3 * quarter):
        centre_us = (300.0 + math.hypot(100.0, arc_mm)) / C_MM_PER_US + centre_after_start_us
        assert envelope_peak_us(env, centre_us, half_width_us=8.0) == pytest.approx(centre_us, abs=0.5)
        assert env[sample_at_us(centre_us)] > 0.005 * 0.1  # over 0.5 % of the direct arrival
    gap_us = (300.0 + math.hypot(100.0, 2 * quarter)) / C_MM_PER_US + centre_after_start_us
    assert env[sample_at_us(gap_us)] < 0.1 * env[sample_at_us((300.0 + math.hypot(100.0, 3 * quarter))
                                                             / C_MM_PER_US + centre_after_start_us)]


def test_antipodal_receiver_sees_both_ways_round_at_equal_time_and_amplitude() -> None:
    circ = 350.0
    defect = ActiveDefect("notch", 100.0, 0.0, 0.2, 0.2j, -0.05 + 0j, 20.0)
    arr = scattered_arrivals(defect, np.array([circ / 2]), 400.0, -300.0, 700.0, 0.0, circ, 36.8, 2000.0)
    first = np.sort(arr.path_mm[0])[:2]
    expected = 100.0 + math.hypot(300.0, circ / 2)
    np.testing.assert_allclose(first, expected)
    amps = arr.amplitude[0][np.isclose(arr.path_mm[0], expected)]
    assert amps.size == 2 and amps[0] == pytest.approx(amps[1])


def test_ring_averaged_backscatter_equals_the_notch_ring_reflection_coefficient() -> None:
    # Oracle: summing the point-scatterer field round a dense ring must give back the 1-D
    # (axisymmetric) reflection coefficient R_T = i * CSAL * sin(k w) the strength was derived from.
    rings = RingSpec(n_transducers=64, transducer_width_mm=1.0, transducer_length_mm=0.0)
    scn = node(pipe=NO_ENDS, rings=rings, defects=[notch(600.0, 90.0)])  # behind the Rx ring
    ring_mean = (volts(scn) - volts(scn.model_copy(update={"defects": []}))).mean(axis=0)
    t_s = np.arange(scn.acquisition.n_samples) / FS
    from mocknode.physics import hann_pulse

    reference = 0.1 * hann_pulse(t_s - 800.0 / (C_MM_PER_US * 1e6), 85e3, 5)
    za, zr = hilbert(ring_mean), hilbert(reference)
    ratio = np.vdot(zr, za) / np.vdot(zr, zr)
    r_t = notch_ring_reflection(scn.defects[0].size, scn.pipe, wavelength_mm(scn))
    assert abs(ratio - r_t) < 0.1 * abs(r_t)


def test_receiver_behind_a_notch_sees_the_direct_arrival_reduced_and_delayed() -> None:
    scn = node(pipe=NO_ENDS, defects=[notch(200.0, 90.0)])
    damaged, clean = volts(scn), volts(scn.model_copy(update={"defects": []}))
    window = slice(sample_at_us(400 / C_MM_PER_US - 2), sample_at_us(400 / C_MM_PER_US + 20))
    behind, opposite = 4, 12  # 90 deg and 270 deg of 16
    za, zb = hilbert(damaged[behind])[window], hilbert(clean[behind])[window]
    ratio = np.vdot(zb, za) / np.vdot(zb, zb)
    assert 0.95 < abs(ratio) < 0.995  # a shadow of a few percent
    assert np.angle(ratio) < 0  # phase lag = delay
    far = np.abs(damaged[opposite][window]).max() / np.abs(clean[opposite][window]).max()
    assert far == pytest.approx(1.0, abs=0.01)


def test_paper_mass_changes_the_direct_amplitude_by_one_to_five_percent() -> None:
    scn = node(pipe=NO_ENDS, rings=RingSpec(n_transducers=8), excitation=ExcitationSpec(frequency_hz=75e3),
               defects=[DefectSpec(kind="mass", axial_mm=200.0, angle_deg=90.0, size={})])
    damaged, clean = volts(scn), volts(scn.model_copy(update={"defects": []}))
    window = slice(0, sample_at_us(400 / C_MM_PER_US + 70))
    change = 1 - np.abs(damaged[2][window]).max() / np.abs(clean[2][window]).max()  # receiver at 90 deg
    assert 0.01 < change < 0.05


def test_temperature_rise_of_10c_delays_the_direct_arrival_by_0p1_percent() -> None:
    scn = node(pipe=NO_ENDS)
    cool, warm = hilbert(volts(scn, 20.0)[0]), hilbert(volts(scn, 30.0)[0])
    delay_s = np.angle(np.vdot(warm, cool)) / (2 * math.pi * 85e3)  # phase of warm behind cool
    expected_s = 400e-3 / 3130.0 * (1 / (1 - 1e-3) - 1)
    assert delay_s == pytest.approx(expected_s, rel=0.05)


def test_temperature_follows_the_daily_cycle_with_jitter_from_the_rng() -> None:
    scn = node(temperature=TemperatureSpec(mean_c=15.0, daily_amplitude_c=4.0, period_s=100.0, jitter_c=0.0))
    assert temperature_at(scn, 25.0, np.random.default_rng(0)) == pytest.approx(19.0)
    jittery = scn.model_copy(update={"temperature": scn.temperature.model_copy(update={"jitter_c": 0.5})})
    temps = [temperature_at(jittery, 0.0, np.random.default_rng(s)) for s in range(400)]
    assert np.std(temps) == pytest.approx(0.5, rel=0.15)


def test_noise_rms_falls_with_the_square_root_of_averaging() -> None:
    def noise_rms(averaging: int) -> float:
        scn = node(acquisition=QUIET.model_copy(update={"noise_v_rms": 0.01, "averaging": averaging}))
        return float(np.std(volts(scn, noise=True) - volts(scn)))

    assert noise_rms(1) == pytest.approx(0.01, rel=0.05)
    assert noise_rms(1) / noise_rms(100) == pytest.approx(10.0, rel=0.05)


def test_quantisation_clips_at_full_scale() -> None:
    scn = node(acquisition=QUIET.model_copy(update={"direct_amplitude_v": 0.3, "adc_full_scale_v": 0.2}))
    acq = acquire(scn, 0.0, np.random.default_rng(0))
    assert acq.codes.dtype == np.int16
    assert acq.codes.max() == 511 and acq.codes.min() == -512
    assert acq.volts_per_code == pytest.approx(0.2 / 512)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=1, max_size=50), st.integers(2, 16))
def test_quantised_codes_are_within_half_a_code_or_clipped(values: list[float], bits: int) -> None:
    v = np.array(values)
    codes, step = quantise_volts(v, bits, 1.0)
    half = 2 ** (bits - 1)
    inside = (v > -1.0) & (v < (half - 1) * step)
    assert np.all(np.abs(codes[inside] * step - v[inside]) <= step / 2 + 1e-12)
    assert codes.min() >= -half and codes.max() <= half - 1


def test_decimation_keeps_every_receiver_and_one_sample_in_factor() -> None:
    codes = acquire(node(), 0.0, np.random.default_rng(0)).codes
    sub = decimate_codes(codes, 10)
    assert sub.shape == (16, 600) and sub.dtype == np.int16
    np.testing.assert_array_equal(sub, codes[:, ::10])
    box = decimate_codes(codes, 10, method="boxcar")
    assert box.shape == (16, 600)
    np.testing.assert_array_equal(box[:, 0], np.rint(codes[:, :10].mean(axis=1)))
    assert decimate_codes(codes[:, :5995], 10).shape == (16, 600)  # ceil(599.5)
    with pytest.raises(PhysicsError):
        decimate_codes(codes, 0)


def test_defect_is_absent_before_it_appears_and_present_after() -> None:
    scn = node(defects=[notch(200.0, 90.0, appears_at_s=100.0)])
    clean = volts(scn.model_copy(update={"defects": []}))
    assert defects_at(scn, 99.9) == []
    np.testing.assert_array_equal(volts(scn, elapsed_s=99.9), clean)
    assert [d.kind for d in defects_at(scn, 100.0)] == ["notch"]
    assert np.abs(volts(scn, elapsed_s=100.0) - clean).max() > 0.005


def test_growing_defect_ramps_linearly_to_its_final_strength() -> None:
    growth = GrowthSpec(start_strength=0.1, final_strength=0.3, grow_duration_s=50.0)
    scn = node(defects=[notch(200.0, 90.0, appears_at_s=10.0, growth=growth)])
    assert [defects_at(scn, t)[0].strength for t in (10.0, 35.0, 60.0, 1e6)] == pytest.approx([0.1, 0.2, 0.3, 0.3])


def test_same_seed_same_acquisition_and_different_seed_differs() -> None:
    scn = node(acquisition=QUIET.model_copy(update={"noise_v_rms": 5e-3}),
               temperature=TemperatureSpec(jitter_c=0.2), defects=[notch(150.0, 45.0)])
    a = acquire(scn, 3.0, np.random.default_rng(42))
    b = acquire(scn, 3.0, np.random.default_rng(42))
    c = acquire(scn, 3.0, np.random.default_rng(43))
    np.testing.assert_array_equal(a.codes, b.codes)
    assert a.temperature_c == b.temperature_c
    assert not np.array_equal(a.codes, c.codes)


def test_acquisition_becomes_a_measurement_with_the_scenario_geometry() -> None:
    scn = node(rings=RingSpec(n_transducers=8, tx_axial_mm=250.0))
    acq = acquire(scn, 7.0, np.random.default_rng(1))
    m = acq.to_measurement(scn)
    assert m.traces.dtype == np.float32 and m.traces.shape == (8, 6000)
    np.testing.assert_allclose(m.traces, acq.codes * acq.volts_per_code, rtol=1e-6)
    np.testing.assert_allclose(m.rx_angles_deg, np.arange(8) * 45.0)
    assert (m.tx_rx_distance_mm, m.pipe_length_mm, m.tx_axial_mm) == (400.0, 1000.0, 250.0)
    assert m.circumference_mm == pytest.approx(math.pi * 114.6)
