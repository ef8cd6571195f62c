"""The default method on the independent full-wave dev set (../shared/fullwave-dev), where present.

The dev set is not shipped with the repository (nor with CI): these tests skip when it is absent,
even under CI=true; bench/bench_fullwave.py is what must not skip. Each test is one case that a
fix in imaging/ was made for, checked on data the imaging did not make.
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from imaging.analysis import analyze
from imaging.echofit import fit_smooth_echoes
from imaging.formats import load_measurement
from imaging.multidefect import FIT_WRAPS
from imaging.multipath import path_model_for
from imaging.pipeline import AssessSettings, assess
from imaging.scene import Scene
from imaging.timing import surface_distance_mm

DEV = Path(__file__).resolve().parents[2].parent / "shared" / "fullwave-dev"
pytestmark = pytest.mark.skipif(not (DEV / "manifest.json").is_file(),
                                reason=f"the full-wave dev set is not here ({DEV}); it is not shipped with the repo")


def _pair(case: str):
    return load_measurement(DEV / f"{case}_baseline.npz"), load_measurement(DEV / f"{case}_current.npz")


def _errors(defects, truths, circumference_mm=360.0):
    return [min((surface_distance_mm(d.axial_mm, d.angle_deg, z, a, circumference_mm) for d in defects),
                default=float("inf")) for z, a in truths]


def test_both_of_two_equal_notches_are_found():
    # With one free amplitude per path *and receiver*, the first notch's fit also absorbed the
    # second's echoes (DI 0.15 before, 0.03 after): only the stronger was reported.
    base, cur = _pair("n16_reflecting_two_120_300_280_100")
    result = assess(cur, [base], AssessSettings())
    assert max(_errors(result.defects, [(120.0, 300.0), (280.0, 100.0)])) < 30.0


@pytest.mark.parametrize("case", ["m8_reflecting_mass_150_45_noisy", "n16_absorbing_notch_150_30"])
def test_a_position_the_map_cannot_pin_down_gets_a_region_that_holds_the_truth(case):
    # A near-rigid mass on an 8-transducer ring (residual ~40 % of the direct arrival) and a notch
    # without end echoes: the estimate is 30-50 mm off; its stated region must say so.
    base, cur = _pair(case)
    truth = {"m8_reflecting_mass_150_45_noisy": (150.0, 45.0), "n16_absorbing_notch_150_30": (150.0, 30.0)}[case]
    result = analyze(base, cur)
    nearest = min(result.defects, key=lambda d: surface_distance_mm(d.axial_mm, d.angle_deg, *truth, 360.0))
    assert nearest.region.contains(nearest.axial_mm, nearest.angle_deg, *truth, 360.0)


def test_two_notches_are_reported_as_two_defects_not_three():
    # With the notches' echoes removed by the map's isotropic model, the directional part of
    # their scattered fields imaged as a third defect at 392 mm 180 deg (DI 0.06 before the
    # re-location pass); letting the notches' echoes follow a first-order pattern explains
    # more of the record than a scatterer there does, so it is ruled out.
    base, cur = _pair("n16_reflecting_two_120_300_280_100")
    result = assess(cur, [base], AssessSettings())
    assert len(result.defects) == 2
    assert max(_errors(result.defects, [(120.0, 300.0), (280.0, 100.0)])) < 30.0


@pytest.mark.parametrize("case", ["n16_absorbing_two_notch_mass", "n16_absorbing_two_notch_mass_noisy"])
def test_a_notch_beside_a_near_rigid_mass_is_found_as_the_second_defect(case):
    # The notch's DI is 0.19 of the mass's (0.13 against 0.69, the defect-free peak 0.005): below the
    # former 0.3 relative gate it was never reported. Faint later peaks now go down to 0.15 of the
    # first and must beat the found defects' second-order directional pattern instead.
    base, cur = _pair(case)
    result = analyze(base, cur)
    assert len(result.defects) == 2
    mass, notch = result.defects
    assert _errors([mass], [(300.0, 20.0)])[0] < 10.0
    assert _errors([notch], [(100.0, 180.0)])[0] < 30.0
    assert notch.di < 0.3 * mass.di  # strongest first; the notch is the faint one


@pytest.mark.parametrize("case", ["m8_absorbing_mass_150_45", "m8_absorbing_mass_150_45_noisy"])
def test_a_sparse_rings_defect_is_placed_where_its_echoes_are_best_explained(case):
    # 8 elements at 75 kHz, no end echoes: the near-rigid mass's map peaks 10 mm past it (the map
    # leans on a few receivers and the directional field pulls the peak); its echoes, fitted round
    # the pipe six times with a first-order pattern, are best explained 2-3 mm from it. The map's
    # peak still gives the confidence: the region is the one the map states.
    base, cur = _pair(case)
    result = analyze(base, cur)
    (mass,) = result.defects
    assert _errors([mass], [(150.0, 45.0)])[0] < 5.0
    assert mass.region.localized and mass.region.contains(mass.axial_mm, mass.angle_deg, 150.0, 45.0, 360.0)


@pytest.mark.parametrize("case", ["m8_absorbing_mass_150_45", "m8_absorbing_mass_150_45_noisy"])
def test_a_mass_without_end_echoes_is_reported_once(case):
    # A near-rigid mass on an 8-transducer ring: the leftover of its fit imaged as a second
    # defect at 232 mm 225 deg (DI 0.25, 0.6 of the mass's).
    base, cur = _pair(case)
    result = analyze(base, cur)
    assert len(result.defects) == 1
    assert _errors(result.defects, [(150.0, 45.0)])[0] < 50.0


@pytest.mark.parametrize("case", ["m8_reflecting_mass_150_45_noisy", "m8_reflecting_light_350_0",
                                  "n16_absorbing_two_notch_mass_noisy"])
def test_monitoring_reports_a_strong_defect_as_a_defect_not_as_no_valid_baseline(case):
    # These leave 9-17 % of the record unexplained against their own baseline, above the 5 % bound:
    # before 2026-12-03 the gateway read them as "no valid baseline" (a blind node, a warning).
    from imaging.compensation import DEFAULT_MAX_COMPENSATED_STRETCH

    base, cur = _pair(case)
    truth = {"m8_reflecting_mass_150_45_noisy": (150.0, 45.0), "m8_reflecting_light_350_0": (350.0, 0.0),
             "n16_absorbing_two_notch_mass_noisy": (300.0, 20.0)}[case]
    result = assess(cur, [base], AssessSettings(max_compensated_stretch=DEFAULT_MAX_COMPENSATED_STRETCH))
    assert result.valid_baseline and result.strong_change is not None
    # Found where it is, within its stated 90 % region (the 16-ring near-rigid mass without end echoes,
    # placed by its echo fit since 2026-12-06, is 10.2 mm off on this coarse grid; the map's peak was 3).
    nearest = min(result.defects, key=lambda d: _errors([d], [truth])[0])
    assert _errors([nearest], [truth])[0] < 15.0
    assert nearest.region.contains(nearest.axial_mm, nearest.angle_deg, *truth, 360.0)


def test_monitoring_abstains_on_a_baseline_of_the_same_pipe_with_other_ends():
    _, cur = _pair("m8_reflecting_mass_150_45")
    other, _ = _pair("m8_absorbing_mass_150_45")
    result = assess(cur, [other], AssessSettings())
    assert not result.valid_baseline and result.defects == []


@pytest.mark.parametrize("case, truth, elsewhere", [
    ("n16_reflecting_notch_250_200", (250.0, 200.0), (150.0, 290.0)),
    ("m8_reflecting_mass_150_45", (150.0, 45.0), (250.0, 135.0)),
])
def test_a_defects_echoes_are_fitted_along_the_turns_its_wave_takes_round_the_pipe(case, truth, elsewhere):
    # The scattered wave keeps circling the pipe within the record: fitted along the map's two legs
    # (either way round) a notch's / a mass's echoes leave 34 % / 47 % of the record, along
    # FIT_WRAPS legs 7 % / 12 % (measured). A point elsewhere explains little with as many legs.
    base, cur = _pair(case)
    residual = base.traces.astype(np.float64) - cur.traces
    scene = Scene.of(base, path_model_for(base))
    energy = float(np.sum(residual**2))

    def left(wraps: int, at: tuple[float, float]) -> float:
        model = dataclasses.replace(scene.model, wraps=wraps)
        fitted = fit_smooth_echoes(residual, dataclasses.replace(scene, model=model), [at])[0]
        return float(np.sum((residual - fitted)**2)) / energy

    assert left(FIT_WRAPS, truth) < 0.5 * left(2, truth)
    assert left(FIT_WRAPS, truth) < 0.2
    assert left(FIT_WRAPS, elsewhere) > 0.5
