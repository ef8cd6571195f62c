"""Localization accuracy and false alarms on the mock node's physics: the paper's method vs the default.

Cases (paper, FE section): a 20 x 10 x 2 mm notch at 90 deg and 100/200/300 mm from the Tx ring,
and at 200 mm and 0/157.5/315 deg (16 transducers, 85 kHz); a 10 kg added mass at 90 deg and
100/200/300 mm (8 transducers, 75 kHz); each with reflecting and with absorbing pipe ends.
Conditions: clean (no receiver noise; the 10-bit ADC still quantises), and noisy (the node's
default receiver noise) with the current record +3 degC warmer than the baseline, with and
without compensation; two notches at once; a false-alarm campaign of defect-free records
with noise and +-2 degC drift. Prints markdown tables (docs/accuracy.md holds a copy).

    .venv/bin/python bench/bench_accuracy.py [--campaign 1000] [--skip-features]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, replace  # noqa: E402

import numpy as np  # noqa: E402

from imaging.detection import calibrate_threshold, default_threshold  # noqa: E402
from imaging.measurement import Measurement  # noqa: E402
from imaging.pipeline import AssessSettings, assess  # noqa: E402
from imaging.timing import surface_distance_mm  # noqa: E402
from mocknode.physics import Acquisition, quantise_volts, simulate_volts  # noqa: E402
from mocknode.scenario import (  # noqa: E402
    AcquisitionSpec,
    DefectSpec,
    ExcitationSpec,
    NodeScenario,
    PipeSpec,
    RingSpec,
)

WALL_MM = 4.0  # paper, Table 1
NOISE_V_RMS = AcquisitionSpec().noise_v_rms  # the node's default receiver noise per shot


@dataclass(frozen=True)
class Case:
    name: str
    kind: str
    positions: tuple[tuple[float, float], ...]
    n_transducers: int
    frequency_hz: float


PAPER_CASES = [
    *(Case(f"notch {z:.0f} mm 90 deg", "notch", ((z, 90.0),), 16, 85e3) for z in (100.0, 200.0, 300.0)),
    *(Case(f"notch 200 mm {a:g} deg", "notch", ((200.0, a),), 16, 85e3) for a in (0.0, 157.5, 315.0)),
    *(Case(f"mass {z:.0f} mm 90 deg", "mass", ((z, 90.0),), 8, 75e3) for z in (100.0, 200.0, 300.0)),
]
TWO_NOTCHES = Case("two notches", "notch", ((150.0, 45.0), (300.0, 225.0)), 16, 85e3)


def scenario(case: Case, ends: str, noise_v_rms: float) -> NodeScenario:
    return NodeScenario(
        node_id="bench",
        pipe=PipeSpec(ends=ends, wall_mm=WALL_MM),
        rings=RingSpec(n_transducers=case.n_transducers),
        excitation=ExcitationSpec(frequency_hz=case.frequency_hz),
        acquisition=AcquisitionSpec(noise_v_rms=noise_v_rms),
        defects=[DefectSpec(kind=case.kind, axial_mm=z, angle_deg=a) for z, a in case.positions],
    )


def record(scn: NodeScenario, temperature_c: float, rng: np.random.Generator) -> Measurement:
    """One acquisition at a given pipe temperature: physics, noise, 10-bit ADC."""
    volts = simulate_volts(scn, elapsed_s=0.0, temperature_c=temperature_c, rng=rng)
    acq = scn.acquisition
    codes, volts_per_code = quantise_volts(volts, acq.adc_bits, acq.adc_full_scale_v)
    return Acquisition(codes, volts_per_code, acq.fs_hz, acq.t0_s, temperature_c, 0.0).to_measurement(scn)


def errors_mm(result, case: Case, circumference_mm: float) -> list[float]:
    """Per true position, the distance to the nearest reported estimate (the peak if none detected)."""
    estimates = [(d.axial_mm, d.angle_deg) for d in result.defects] or [(result.peak.axial_mm, result.peak.angle_deg)]
    return [min(surface_distance_mm(e[0], e[1], z, a, circumference_mm) for e in estimates) for z, a in case.positions]


def settings_for(method: str, feature: str = "analytic", compensate: bool = True, max_defects: int = 3):
    return AssessSettings(method=method, feature=feature, compensate=compensate, wall_mm=WALL_MM,
                          max_defects=max_defects)


METHODS = {"paper": settings_for("paper"), "multipath": settings_for("multipath")}


def run_condition(title: str, cases, ends_list, noise_v_rms: float, delta_c: float, methods: dict, seed: int):
    rng = np.random.default_rng(seed)
    rows, errs = [], {name: [] for name in methods}
    times = {name: [] for name in methods}
    for ends in ends_list:
        for case in cases:
            base_scn, cur_scn = scenario(replace(case, positions=()), ends, noise_v_rms), scenario(case, ends, noise_v_rms)
            baseline, current = record(base_scn, 20.0, rng), record(cur_scn, 20.0 + delta_c, rng)
            cells = []
            for name, settings in methods.items():
                result = assess(current, [baseline], settings)
                times[name].append(result.elapsed_ms)
                if not result.valid_baseline:
                    cells.append("abstained")
                    continue
                err = errors_mm(result, case, current.circumference_mm)
                errs[name].extend(err)
                est = "; ".join(f"{d.axial_mm:.0f} mm {d.angle_deg:.0f}\u00b0" for d in result.defects) or (
                    f"({result.peak.axial_mm:.0f} mm {result.peak.angle_deg:.0f}\u00b0, not detected)")
                cells.append(f"{est} | {', '.join(f'{e:.1f}' for e in err)}")
            truth = "; ".join(f"{z:.0f} mm {a:g}\u00b0" for z, a in case.positions)
            rows.append(f"| {ends} | {case.name} | {truth} | " + " | ".join(cells) + " |")
    header = "| ends | case | true | " + " | ".join(f"{n} estimate | {n} error mm" for n in methods) + " |"
    print(f"\n### {title}\n")
    print(header)
    print("|" + "---|" * (3 + 2 * len(methods)))
    print("\n".join(rows))
    print()
    for name in methods:
        e = errs[name]
        if e:
            print(f"- {name}: median {statistics.median(e):.1f} mm, worst {max(e):.1f} mm over {len(e)} positions; "
                  f"median {statistics.median(times[name]):.0f} ms per assessment")
    return errs


def campaign(n: int, seed: int) -> None:
    """Defect-free records (n per end condition), noise, temperature uniform in 20 +- 2 degC, one 20 degC baseline."""
    rng = np.random.default_rng(seed)
    case = replace(PAPER_CASES[0], positions=())
    print(f"\n### False-alarm campaign: {n} defect-free records, noise, 20 +- 2 degC, one 20 degC baseline\n")
    print("| ends | method | threshold | false alarms | peak DI mean | peak DI max | mean + 3.09 sd (1e-3) | stretch used |")
    print("|---|---|---|---|---|---|---|---|")
    for ends in ("reflecting", "absorbing"):
        scn = scenario(case, ends, NOISE_V_RMS)
        baseline = record(scn, 20.0, rng)
        peaks = {"paper": [], "multipath": []}
        stretched = 0
        start = time.perf_counter()
        for _ in range(n):
            current = record(scn, 20.0 + rng.uniform(-2.0, 2.0), rng)
            for name in peaks:
                result = assess(current, [baseline], replace(METHODS[name], max_defects=1))
                peaks[name].append(result.peak_di if result.valid_baseline else np.nan)
                stretched += name == "multipath" and result.baseline is not None and result.baseline.stretch != 0.0
        for name, values in peaks.items():
            values = np.asarray(values)
            thr = default_threshold(name, "analytic" if name == "multipath" else "squared")
            cal = calibrate_threshold(values[np.isfinite(values)], false_alarm_rate=1e-3)
            print(f"| {ends} | {name} | {thr:.3g} | {int(np.sum(values >= thr))} / {n} "
                  f"({int(np.sum(~np.isfinite(values)))} abstained) | {np.nanmean(values):.3g} | {np.nanmax(values):.3g} "
                  f"| {cal.threshold:.3g} | {stretched if name == 'multipath' else '-'} |")
        print(f"<!-- {ends}: {time.perf_counter() - start:.0f} s -->")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=int, default=500, help="defect-free records per end condition (x2)")
    parser.add_argument("--skip-features", action="store_true", help="skip the feature comparison")
    args = parser.parse_args()
    ends = ("reflecting", "absorbing")
    start = time.perf_counter()
    run_condition("Clean (no receiver noise, same temperature)", PAPER_CASES, ends, 0.0, 0.0, METHODS, 1)
    run_condition("Noise, current +3 degC, with compensation (OBS + BSS)", PAPER_CASES, ends, NOISE_V_RMS, 3.0,
                  METHODS, 2)
    uncompensated = {n: replace(s, compensate=False) for n, s in METHODS.items()}
    run_condition("Noise, current +3 degC, without compensation", PAPER_CASES, ends, NOISE_V_RMS, 3.0,
                  uncompensated, 2)
    run_condition("Two notches at once (noise, same temperature)", [TWO_NOTCHES], ends, NOISE_V_RMS, 0.0, METHODS, 3)
    if not args.skip_features:
        features = {f"multipath/{f}": settings_for("multipath", f) for f in ("analytic", "envelope", "squared")}
        run_condition("Features compared (noise, same temperature)", PAPER_CASES, ends, NOISE_V_RMS, 0.0, features, 4)
    if args.campaign > 0:
        campaign(args.campaign, 5)
    print(f"\n<!-- total {time.perf_counter() - start:.0f} s -->")


if __name__ == "__main__":
    main()
