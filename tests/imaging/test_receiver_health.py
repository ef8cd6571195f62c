"""Receiver health on physics the check was not written beside: a scatterer in front of a receiver
changes what that receiver records, but it is not a sensor fault; a fault of the channel is one,
beside a scatterer and under a temperature change too (the project's own full-wave engine, fullwave/)."""
import dataclasses

import numpy as np
import pytest

from fullwave.defects import Mass
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.arrivals import direct_arrival
from imaging.health import MAX_DELAY_PERIODS, NO_LIKENESS, SAME_SHAPE, channel_changes, check_receivers
from imaging.measurement import Measurement

LIGHT_MASS_KG, LIGHT_MASS_MM = 1.0, 20.0


def _ring(ends: str, temperature_c: float = 20.0) -> SimulationSpec:
    return SimulationSpec(pipe=PipeModel(length_mm=600.0, ends=ends),  # type: ignore[arg-type]
                          rings=RingLayout(tx_axial_mm=150.0, n_transducers=8, tx_rx_distance_mm=300.0),
                          excitation_hz=75e3, cell_mm=2.0, n_samples=4000, temperature_c=temperature_c)


def _pair(ends: str, axial_mm: float, angle_deg: float, temperature_c: float = 20.0, kg: float = LIGHT_MASS_KG):
    mass = Mass(axial_mm=axial_mm, angle_deg=angle_deg, mass_kg=kg,
                diameter_mm=LIGHT_MASS_MM if kg == LIGHT_MASS_KG else 6.0)
    current = simulate(_ring(ends, temperature_c).with_changes(defects=(mass,)))
    return simulate(_ring(ends)), current


def _with_channel(current: Measurement, rx: int, gain: float = 1.0, delay_s: float = 0.0,
                  noise_v: float = 0.0) -> Measurement:
    """``current`` with one receiver channel scaled, delayed (exactly, by a phase ramp) and noisy."""
    traces = current.traces.astype(np.float64).copy()
    spectrum = np.fft.rfft(traces[rx], 2 * current.n_samples)
    freqs = np.fft.rfftfreq(2 * current.n_samples, 1.0 / current.fs_hz)
    row = np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * delay_s))[: current.n_samples]
    noise = np.random.default_rng(rx).normal(0.0, noise_v, current.n_samples) if noise_v else 0.0
    traces[rx] = gain * row + noise
    return dataclasses.replace(current, traces=traces.astype(current.traces.dtype))


@pytest.mark.parametrize(("ends", "axial_mm", "angle_deg", "kg"), [
    ("reflecting", 250.0, 0.0, LIGHT_MASS_KG),  # 50 mm before the Rx ring, in line with receiver 0
    ("reflecting", 40.0, 0.0, LIGHT_MASS_KG),  # just past the Tx ring: every receiver's arrival changes
    ("absorbing", 250.0, 45.0, LIGHT_MASS_KG),
    ("absorbing", 40.0, 0.0, 10.0),  # a near-rigid point
])
def test_a_scatterer_in_front_of_receivers_is_not_a_sensor_fault(ends, axial_mm, angle_deg, kg):
    baseline, current = _pair(ends, axial_mm, angle_deg, kg=kg)
    # What made the direct arrival's own peak a poor judge: it "moves" by far more than a quarter period.
    moved = direct_arrival(current).time_s - direct_arrival(baseline).time_s
    assert np.ptp(moved) > MAX_DELAY_PERIODS / current.excitation_hz
    assert check_receivers(baseline, current) == []


@pytest.mark.parametrize("temperature_c", [28.0, 32.0, 10.0])
def test_a_scatterer_and_a_temperature_change_are_not_a_sensor_fault(temperature_c):
    baseline, current = _pair("absorbing", 150.0, 20.0, temperature_c)
    assert check_receivers(baseline, current) == []


CUT = {"gain": 0.0, "noise_v": 1e-3}  # the cable cut: noise alone (scaled to the channel below)


@pytest.mark.parametrize(("rx", "change", "kind"), [
    *[(rx, change, kind) for rx in (0, 3) for change, kind in [  # 0: in the mass's shadow; 3: clear of it
        ({"gain": 0.3}, "amplitude"),
        ({"gain": 2.5}, "amplitude"),
        ({"delay_s": 0.3 / 75e3}, "timing"),
        ({"delay_s": 0.6 / 75e3}, "timing"),
        ({"delay_s": 1e-4}, "timing"),  # beyond the burst's length
        (CUT, "no_signal"),
    ]],
    (3, {"delay_s": 1.0 / 75e3}, "timing"),  # a whole period: not taken for a cycle skip
])
def test_a_channel_fault_beside_a_scatterer_is_named(rx, change, kind):
    baseline, current = _pair("reflecting", 250.0, 0.0, temperature_c=24.0)
    if change is CUT:
        change = {**change, "noise_v": 0.05 * float(np.std(current.traces[rx]))}
    faults = check_receivers(baseline, _with_channel(current, rx, **change))
    assert [(f.rx_index, f.kind) for f in faults] == [(rx, kind)]
    if kind == "timing" and rx == 3:
        assert faults[0].delay_s == pytest.approx(change["delay_s"], abs=0.05 / 75e3)


@pytest.mark.parametrize(("gain", "kind"), [(0.2, "amplitude"), (4.0, "amplitude"), (0.6, None)])
def test_a_channel_whose_response_changed_shape_is_named_when_far_weaker_or_stronger(gain, kind):
    # A debond that also reshapes the transducer's response: the record no longer alike (a second,
    # delayed copy of it), and weakened or strengthened beyond anything a defect did on the full-wave sets.
    baseline, current = _pair("reflecting", 250.0, 0.0)
    reshaped = _with_channel(current, 3, delay_s=3.0 / 75e3)
    traces = current.traces.astype(np.float64)
    traces[3] = gain * (traces[3] + reshaped.traces[3])
    current = dataclasses.replace(current, traces=traces.astype(current.traces.dtype))
    change = channel_changes(baseline, current)
    assert NO_LIKENESS < change.likeness[3] < SAME_SHAPE  # reshaped, not gone
    faults = check_receivers(baseline, current)
    assert [(f.rx_index, f.kind) for f in faults] == ([] if kind is None else [(3, kind)])


def test_a_small_delay_is_no_fault():
    baseline, current = _pair("absorbing", 250.0, 45.0)
    assert check_receivers(baseline, _with_channel(current, 5, delay_s=0.15 / 75e3)) == []
