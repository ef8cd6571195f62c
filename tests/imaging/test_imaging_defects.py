"""Several defects, sensor faults, confidence and severity: what assess() reports beyond one peak."""
import math
from dataclasses import replace

import numpy as np
import pytest

from imaging import multidefect
from imaging.echofit import burst_pair, fit_smooth_echoes
from imaging.localize import Estimate
from imaging.multipath import path_model_for
from imaging.paths import scalar_paths
from imaging.pipeline import AssessSettings, assess
from imaging.scene import Scene
from imaging.severity import SECONDS_PER_MONTH, TrendError, severity_trend
from imaging.timing import surface_distance_mm
from mocknode.physics import Acquisition, quantise_volts, simulate_volts
from mocknode.scenario import (
    DefectSpec,
    ExcitationSpec,
    ModeConversion,
    ModesSpec,
    NodeScenario,
    NotchSize,
    PipeSpec,
    RingSpec,
)
from tests.support.synthetic import CIRCUMFERENCE_MM, baseline_and_scatterers

SETTINGS = AssessSettings()


def _errors(defects, truths):
    return [
        min(surface_distance_mm(d.axial_mm, d.angle_deg, z, a, CIRCUMFERENCE_MM) for d in defects)
        for z, a in truths
    ]


def test_two_scatterers_are_both_found_where_each_images_alone():
    scatterers = [(120.0, 60.0, 0.05), (290.0, 230.0, 0.04)]
    truths = [(z, a) for z, a, _ in scatterers]
    base, cur = baseline_and_scatterers(scatterers, noise_rms=5e-4, seed=2)
    result = assess(cur, [base], SETTINGS)
    assert len(result.defects) == 2
    # No end echoes: each is placed by its echoes (imaging/multidefect.py ``echo_placed``), fitted
    # jointly with the other's. Measured: 2.4 and 0.5 mm, alone 0.4 and 0.6; the maps' peaks had been
    # 5.2 and 0.9 mm (alone 13 mm for the one at 120 mm).
    alone = [assess(c, [b], SETTINGS).defects[0] for b, c in
             (baseline_and_scatterers([s], noise_rms=5e-4, seed=2) for s in scatterers)]
    assert max(_errors(alone, truths)) < 2.0
    assert max(_errors(result.defects, truths)) < 3.5
    assert result.defects[0].di >= result.defects[1].di


def test_one_scatterer_is_reported_once():
    base, cur = baseline_and_scatterers([(200.0, 100.0, 0.05)], noise_rms=5e-4, seed=2)
    result = assess(cur, [base], SETTINGS)
    assert len(result.defects) == 1


def test_a_later_maximum_on_a_ring_is_fitted_away_but_not_reported_as_a_defect(monkeypatch):
    # A change at the Tx ring in line with the notch. Along a receiver's line every position gives
    # that receiver the same delay: after the notch, the map's next maximum lies on that line 29.5 mm
    # from the ring, where the change at the ring itself explains more of the record. It is treated
    # as the ring's maximum: fitted, not reported; the notch alone is.
    base, cur = baseline_and_scatterers([(200.0, 100.0, 0.05), (0.0, 100.0, 0.03)], noise_rms=5e-4, seed=2)
    defects = assess(cur, [base], SETTINGS).defects
    assert len(defects) == 1
    assert _errors(defects, [(200.0, 100.0)])[0] < 20.0
    monkeypatch.setattr(multidefect._Search, "ring_instead", lambda *args: None)
    located = assess(cur, [base], SETTINGS).defects
    assert len(located) == 2 and located[1].axial_mm < 40.0 and abs(located[1].angle_deg - 100.0) < 5.0


def test_a_later_maximum_within_half_a_wavelength_of_a_ring_is_not_reported(monkeypatch):
    # In a ring's near field the map's far-field paths do not hold; on full-wave records the
    # maxima there (8-14 mm before the Rx ring, in line with a receiver) were a found defect's
    # shadow on the direct arrival. A weaker scatterer 6 mm before the Rx ring is therefore not
    # reported (the known cost), though it is without the rule.
    base, cur = baseline_and_scatterers([(200.0, 100.0, 0.05), (394.0, 100.0, 0.03)], noise_rms=5e-4, seed=2)
    defects = assess(cur, [base], SETTINGS).defects
    assert len(defects) == 1
    assert _errors(defects, [(200.0, 100.0)])[0] < 20.0
    monkeypatch.setattr(multidefect, "NEAR_RING_WAVELENGTHS", 0.0)
    assert len(assess(cur, [base], SETTINGS).defects) == 2


def test_a_dead_receiver_is_a_sensor_fault_not_damage():
    base, cur = baseline_and_scatterers([], noise_rms=5e-4, seed=8)
    traces = cur.traces.copy()
    traces[5] = np.random.default_rng(1).normal(0, 5e-4, traces.shape[1])  # channel 5 dead: noise only
    dead = replace(cur, traces=traces)
    result = assess(dead, [base], SETTINGS)
    assert [(f.rx_index, f.kind) for f in result.sensor_faults] == [(5, "no_signal")]
    assert not result.detected
    unchecked = assess(dead, [base], replace(SETTINGS, check_health=False))
    # Without the health check the dead channel spoils the assessment: no baseline fits, or "damage".
    assert not unchecked.valid_baseline or unchecked.detected


def test_a_defect_is_still_found_with_a_dead_receiver():
    base, cur = baseline_and_scatterers([(150.0, 200.0, 0.05)], noise_rms=5e-4, seed=8)
    traces = cur.traces.copy()
    traces[3] *= 0.05  # debonded: 5 % of its signal left
    result = assess(replace(cur, traces=traces), [base], SETTINGS)
    assert [f.rx_index for f in result.sensor_faults] == [3]
    assert result.detected and _errors(result.defects, [(150.0, 200.0)])[0] < 10.0


def test_confidence_is_higher_for_a_clean_peak_than_for_noise():
    base, cur = baseline_and_scatterers([(220.0, 300.0, 0.05)], noise_rms=5e-4, seed=4)
    strong = assess(cur, [base], SETTINGS)
    qb, qc = baseline_and_scatterers([], noise_rms=5e-4, seed=4)
    weak = assess(qc, [qb], replace(SETTINGS, threshold=-1.0))  # force the noise peak to be reported
    assert 0.0 <= weak.defects[0].confidence.score < strong.defects[0].confidence.score <= 1.0
    assert strong.defects[0].confidence.width_axial_mm > 0


def test_severity_grows_with_the_scattered_amplitude():
    severities = []
    for amplitude in (0.02, 0.04, 0.08):
        base, cur = baseline_and_scatterers([(200.0, 90.0, amplitude)], seed=1)
        severities.append(assess(cur, [base], SETTINGS).defects[0].severity)
    assert severities[0] < severities[1] < severities[2]
    assert severities[2] / severities[0] == pytest.approx(4.0, rel=0.15)


def test_severity_trend_is_the_rate_per_month():
    t = np.arange(10) * 7 * 86400.0  # weekly
    rate = 0.003
    s = 0.05 + rate * t / SECONDS_PER_MONTH + np.random.default_rng(0).normal(0, 1e-4, t.size)
    trend = severity_trend(t, s)
    assert trend.rate_per_month == pytest.approx(rate, rel=0.05)
    assert trend.n_points == 10 and trend.rate_stderr_per_month < 1e-3
    with pytest.raises(TrendError):
        severity_trend(t[:1], s[:1])


def _mock_record(scn: NodeScenario, temperature_c: float, seed: int):
    v = simulate_volts(scn, elapsed_s=0.0, temperature_c=temperature_c, rng=np.random.default_rng(seed))
    acq = scn.acquisition
    codes, vpc = quantise_volts(v, acq.adc_bits, acq.adc_full_scale_v)
    return Acquisition(codes, vpc, acq.fs_hz, acq.t0_s, temperature_c, 0.0).to_measurement(scn)


@pytest.mark.parametrize(("first", "second"), [((100.0, 90.0), (300.0, 270.0)), ((120.0, 300.0), (280.0, 60.0))])
def test_a_shallow_second_notch_is_still_found_beside_a_deep_one(first, second):
    # bench_defect_gate's 1 mm-deep second notch (DI ~0.06, half the first's): removing the first
    # notch's echoes with a directional pattern per path took a third of the shallow one's
    # wherever their paths overlapped, and it was lost. The pattern only judges later peaks.
    def scenario(defects):
        return NodeScenario(node_id="m", pipe=PipeSpec(ends="reflecting", wall_mm=4.0), defects=defects)

    baseline = _mock_record(scenario([]), 20.0, 1)
    current = _mock_record(scenario([DefectSpec(kind="notch", axial_mm=first[0], angle_deg=first[1]),
                                     DefectSpec(kind="notch", axial_mm=second[0], angle_deg=second[1],
                                                size=NotchSize(depth_mm=1.0))]), 20.0, 2)
    result = assess(current, [baseline], AssessSettings(wall_mm=4.0))
    errors = [min(surface_distance_mm(d.axial_mm, d.angle_deg, z, a, current.circumference_mm) for d in result.defects)
              for z, a in (first, second)]
    assert max(errors) < 10.0
    assert result.defects[0].di > 1.5 * result.defects[1].di  # the shallow one is clearly the weaker


def test_a_change_at_the_tx_ring_is_fitted_away_and_the_defect_behind_it_reported_alone():
    # An 8-ring mass at 100 mm imaged against a 3 degC colder baseline without compensation: the Tx
    # ring's change (what the temperature does there) is a maximum at 0 mm about as strong as the
    # mass's. It was reported as a "defect" and the mass as a later one (behind rivals at the ring,
    # it was often lost). A maximum on the span's end is not located: it is fitted, the mass is
    # reported alone. (Where the groups' powers were added the ring's maximum was the strongest and
    # the mass was found 0.8-1.0 mm off; projected on jointly, the mass is the strongest, and the
    # stretch's leftovers, which the ring's fit does not remove, leave it 9.8-11.1 mm off.)
    def record(defects, temperature_c, seed):
        scn = NodeScenario(node_id="m", pipe=PipeSpec(ends="reflecting", wall_mm=4.0),
                           rings=RingSpec(n_transducers=8), excitation=ExcitationSpec(frequency_hz=75e3),
                           defects=defects)
        return _mock_record(scn, temperature_c, seed)

    settings = AssessSettings(wall_mm=4.0, compensate=False)
    for k in range(4):
        baseline = record([], 20.0, 2 * k)
        current = record([DefectSpec(kind="mass", axial_mm=100.0, angle_deg=90.0)], 23.0, 2 * k + 1)
        result = assess(current, [baseline], settings)
        pixels, grid = result.di_map.pixels, result.di_map.grid
        assert pixels[grid.axial_mm < 2.0].max() > 0.8 * pixels.max()  # the ring's change: as strong as the mass
        assert len(result.defects) == 1
        found = result.defects[0]
        error = surface_distance_mm(found.axial_mm, found.angle_deg, 100.0, 90.0, current.circumference_mm)
        assert error < 15.0 and found.region.localized
        assert abs(found.axial_mm - 100.0) <= found.region.axial_half_mm  # inside its stated region


@pytest.mark.parametrize("n_transducers, frequency_hz", [(8, 75e3), (16, 85e3)])
def test_a_change_at_a_ring_is_reported_when_nothing_located_is_found(n_transducers, frequency_hz):
    # A sound pipe 3 degC warmer than its baseline, without compensation: the change maps onto the
    # Tx ring; once it is fitted nothing located crosses the threshold, so the ring's change is what
    # is reported (a change is never dropped for want of a located one).
    scn = NodeScenario(node_id="m", pipe=PipeSpec(ends="reflecting", wall_mm=4.0),
                       rings=RingSpec(n_transducers=n_transducers), excitation=ExcitationSpec(frequency_hz=frequency_hz))
    result = assess(_mock_record(scn, 23.0, 1), [_mock_record(scn, 20.0, 0)],
                    AssessSettings(wall_mm=4.0, compensate=False))
    assert len(result.defects) == 1
    assert result.defects[0].axial_mm < 2.0


def _directional_echo(scene: Scene, shape: tuple[int, int], z: float, angle: float) -> np.ndarray:
    """A scatterer's echoes along the scene's paths, scaled on every path by 1 + 0.8 cos(bearing)."""
    burst, _ = burst_pair(scene.fs_hz, scene.excitation_hz, scene.cycles)
    echo = np.zeros(shape)
    for m, rx in enumerate(scene.rx_angles_deg):
        gain = 1.0 + 0.8 * math.cos(math.radians(angle - rx))
        for _group, length, w in scalar_paths(scene.model, z, angle - rx):
            start = math.floor((length / (scene.velocity_m_s * 1e3) - scene.t0_s) * scene.fs_hz + 0.5)
            lo, hi = max(start, 0), min(start + burst.size, shape[1])
            if hi > lo:
                echo[m, lo:hi] += gain * w * burst[lo - start:hi - start]
    return echo


def _found(z: float, angle: float, di: float) -> multidefect.Found:
    return multidefect.Found(Estimate(z, angle, di), None, 0.0)  # type: ignore[arg-type]  # no map needed


def test_a_directional_echo_is_removed_by_a_first_order_pattern_and_not_by_one_amplitude():
    # One scatterer whose echo on every path is scaled by 1 + 0.8 cos(bearing) on top of the
    # path's expected amplitude: the fit with orders=1 removes it to rounding; the map's own
    # model (orders=0: one amplitude per path) leaves a fair part of it.
    base, _ = baseline_and_scatterers([], n_samples=3000)
    scene = Scene.of(base, path_model_for(base))
    z, angle = 200.0, 100.0
    echo = _directional_echo(scene, base.traces.shape, z, angle)
    energy = float(np.sum(echo**2))
    left_1 = echo - sum(fit_smooth_echoes(echo, scene, [(z, angle)], orders=1))
    left_0 = echo - sum(fit_smooth_echoes(echo, scene, [(z, angle)], orders=0))
    assert float(np.sum(left_1**2)) < 1e-20 * energy
    assert float(np.sum(left_0**2)) > 0.1 * energy


def test_every_reported_defect_must_explain_more_than_the_others_patterns_once_all_are_found():
    # The search judges a later peak only against the defects found before it; the first, the
    # strongest maximum, was never judged. A point elsewhere that one directional scatterer's
    # echoes (first-order pattern) explain better is dropped, even when it imaged higher; two
    # scatterers are each kept.
    base, _ = baseline_and_scatterers([], n_samples=3000)
    scene = Scene.of(base, path_model_for(base))
    echo = _directional_echo(scene, base.traces.shape, 200.0, 100.0)
    true, leftover = _found(200.0, 100.0, 0.05), _found(320.0, 280.0, 0.08)
    kept = multidefect._confirmed(multidefect._Search(echo, scene), [leftover, true], [])
    assert [f.estimate for f in kept] == [true.estimate]
    two = [(120.0, 60.0, 0.05), (290.0, 230.0, 0.04)]
    base, cur = baseline_and_scatterers(two, n_samples=3000)
    residual = base.traces.astype(np.float64) - cur.traces.astype(np.float64)
    both = [_found(z, a, 0.05) for z, a, _ in two]
    assert len(multidefect._confirmed(multidefect._Search(residual, Scene.of(base, path_model_for(base))), both, [])) == 2


def test_a_faint_later_peak_must_beat_a_second_order_pattern_of_the_found_defects_echoes(monkeypatch):
    # A notch that also converts T(0,1) into flexural and longitudinal modes (bench_accuracy's assumed
    # levels, without ring leakage): the converted waves, imaged as T(0,1), leave a faint peak on the
    # notch's own line (here 77 mm 89 deg, 0.34 of the notch's DI after re-location). Against the first-order
    # pattern it passed as a second defect once later peaks went down to 0.15 of the first; a peak
    # below 0.3 of the first must now explain more than a second-order pattern does, and it does not.
    conversions = [ModeConversion(mode="F(1,1)", ratio=0.5), ModeConversion(mode="F(2,1)", ratio=0.3, phase_deg=60.0),
                   ModeConversion(mode="L(0,1)", ratio=0.2, phase_deg=-45.0),
                   ModeConversion(mode="F(1,3)", ratio=0.3, phase_deg=90.0)]

    def scenario(defects):
        return NodeScenario(node_id="m", pipe=PipeSpec(ends="reflecting", wall_mm=4.0), defects=defects,
                            modes=ModesSpec(conversions=conversions))

    notch = [DefectSpec(kind="notch", axial_mm=300.0, angle_deg=90.0)]
    baseline, current = _mock_record(scenario([]), 20.0, 1), _mock_record(scenario(notch), 20.0, 2)
    result = assess(current, [baseline], AssessSettings(wall_mm=4.0))
    assert len(result.defects) == 1
    assert surface_distance_mm(result.defects[0].axial_mm, result.defects[0].angle_deg, 300.0, 90.0,
                               current.circumference_mm) < 2.0
    monkeypatch.setattr(multidefect, "FAINT_PATTERN_ORDERS", multidefect.PATTERN_ORDERS)
    ghosted = assess(current, [baseline], AssessSettings(wall_mm=4.0))
    assert len(ghosted.defects) == 2 and abs(ghosted.defects[1].angle_deg - 90.0) < 5.0
