"""Localization accuracy and false alarms on the mock node's physics: the paper's method vs the default.

Cases (paper, FE section): a 20 x 10 x 2 mm notch at 90 deg and 100/200/300 mm from the Tx ring,
and at 200 mm and 0/157.5/315 deg (16 transducers, 85 kHz); a 10 kg added mass at 90 deg and
100/200/300 mm (8 transducers, 75 kHz); each with reflecting and with absorbing pipe ends.
Conditions: clean (no receiver noise; the 10-bit ADC still quantises), and noisy (the node's
default receiver noise) with the current record +3 degC warmer than the baseline, with and
without compensation; two notches at once; a false-alarm campaign of defect-free records
with noise and +-2 degC drift. Then the same cases with the other guided modes switched on
(ring leakage of L(0,1), L(0,2) and flexural modes at assumed levels for 8- and 16-transducer
rings, and mode conversion at the defect), with and without a +3 degC change, and their own
false-alarm campaign. Also the notches and masses a quarter and half a receiver pitch off a
receiver's angle, the default map against the one that adds its groups' powers. Prints markdown
tables (docs/accuracy.md holds a copy).

    .venv/bin/python bench/bench_accuracy.py [--campaign 1000] [--skip-features] [--modes-campaign 250]
        [--only-modes]
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
    ModeConversion,
    ModeLeak,
    ModesSpec,
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
# Every position above lies on a receiver's angle (90 deg: a multiple of 22.5 and of 45): where the
# map does best. The same defects a quarter and half a pitch off a receiver (docs/imaging.md "The
# groups' overlap"): 16 rings' pitch 22.5 deg, 8 rings' 45 deg.
OFF_RECEIVER_CASES = [
    *(Case(f"notch {z:.0f} mm {a:g} deg", "notch", ((z, a),), 16, 85e3)
      for z in (100.0, 200.0, 300.0) for a in (95.625, 101.25)),
    *(Case(f"mass {z:.0f} mm {a:g} deg", "mass", ((z, a),), 8, 75e3) for z in (100.0, 200.0, 300.0) for a in (101.25, 112.5)),
]
TWO_NOTCHES = Case("two notches", "notch", ((150.0, 45.0), (300.0, 225.0)), 16, 85e3)


def scenario(case: Case, ends: str, noise_v_rms: float, modes: ModesSpec | None = None) -> NodeScenario:
    return NodeScenario(
        node_id="bench",
        pipe=PipeSpec(ends=ends, wall_mm=WALL_MM),
        rings=RingSpec(n_transducers=case.n_transducers),
        excitation=ExcitationSpec(frequency_hz=case.frequency_hz),
        acquisition=AcquisitionSpec(noise_v_rms=noise_v_rms),
        defects=[DefectSpec(kind=case.kind, axial_mm=z, angle_deg=a) for z, a in case.positions],
        modes=modes or ModesSpec(),
    )


# Assumed leakage levels (amplitude at a receiver relative to the direct T(0,1) arrival; docs/accuracy.md,
# "Other guided modes"). Axisymmetric L(0,1)/L(0,2) from the transducers' imperfect shear polarisation,
# the ring-order flexural modes F(N,1)/F(N,2) that N discrete elements launch (F(16,2) is below its
# 144 kHz cut-off and dies away; F(8,2), cut-off 72 kHz, propagates slowly), and low orders F(1,.)/F(2,.)
# from element-to-element spread. The 8-transducer ring leaks more, as the paper reports.
LEAKS = {
    16: [ModeLeak(mode="L(0,1)", amplitude=0.02), ModeLeak(mode="L(0,2)", amplitude=0.01),
         ModeLeak(mode="F(16,1)", amplitude=0.02), ModeLeak(mode="F(16,2)", amplitude=0.10),
         ModeLeak(mode="F(1,2)", amplitude=0.01, angle_deg=40.0), ModeLeak(mode="F(1,1)", amplitude=0.01, angle_deg=130.0)],
    8: [ModeLeak(mode="L(0,1)", amplitude=0.05), ModeLeak(mode="L(0,2)", amplitude=0.03),
        ModeLeak(mode="F(8,1)", amplitude=0.05), ModeLeak(mode="F(8,2)", amplitude=0.10),
        ModeLeak(mode="F(1,2)", amplitude=0.02, angle_deg=40.0), ModeLeak(mode="F(1,1)", amplitude=0.02, angle_deg=130.0),
        ModeLeak(mode="F(2,1)", amplitude=0.01, angle_deg=75.0)],
}
# Mode conversion at the defect (ratio to the defect's ring-level T(0,1) reflection): into the A0-like
# (L(0,1), F(n,1)) and S0-like (F(1,3)) families; the SH-family F(n,2) scattering is the 2-D SH field itself.
CONVERSIONS = [ModeConversion(mode="F(1,1)", ratio=0.5), ModeConversion(mode="F(2,1)", ratio=0.3, phase_deg=60.0),
               ModeConversion(mode="L(0,1)", ratio=0.2, phase_deg=-45.0), ModeConversion(mode="F(1,3)", ratio=0.3,
                                                                                          phase_deg=90.0)]


def leaky(case: Case, convert: bool, conversion_scale: float = 1.0) -> ModesSpec:
    conversions = [ModeConversion(mode=c.mode, ratio=c.ratio * conversion_scale, phase_deg=c.phase_deg)
                   for c in CONVERSIONS] if convert else []
    return ModesSpec(leaks=LEAKS[case.n_transducers], conversions=conversions)


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


MATCH_MM = 50.0  # a reported defect this close to a true one is its detection (as in bench_fullwave.py)


def region_outcomes(result, case: Case, circumference_mm: float) -> list[tuple[bool, float]]:
    """Per true position detected (a reported defect within MATCH_MM): (inside that defect's stated 90 %
    region, the region's mean half-width in mm). Out of sample: the regions' factors were set on the
    full-wave cases, never on these."""
    out = []
    for z, a in case.positions:
        near = [(surface_distance_mm(d.axial_mm, d.angle_deg, z, a, circumference_mm), d) for d in result.defects]
        if not near:
            continue
        dist, d = min(near, key=lambda x: x[0])
        if dist <= MATCH_MM and d.region is not None:
            out.append((d.region.contains(d.axial_mm, d.angle_deg, z, a, circumference_mm),
                        0.5 * (d.region.axial_half_mm + d.region.circumferential_half_mm)))
    return out


def settings_for(method: str, feature: str = "analytic", compensate: bool = True, max_defects: int = 3):
    return AssessSettings(method=method, feature=feature, compensate=compensate, wall_mm=WALL_MM,
                          max_defects=max_defects)


METHODS = {"paper": settings_for("paper"), "multipath": settings_for("multipath")}


def run_condition(title: str, cases, ends_list, noise_v_rms: float, delta_c: float, methods: dict, seed: int,
                  modes=None):
    """``modes``: None (T(0,1) only) or a function Case -> ModesSpec applied to baseline and current alike."""
    rng = np.random.default_rng(seed)
    rows, errs = [], {name: [] for name in methods}
    times = {name: [] for name in methods}
    regions: dict[str, list[tuple[bool, float]]] = {name: [] for name in methods}
    for ends in ends_list:
        for case in cases:
            spec = modes(case) if modes is not None else None
            base_scn = scenario(replace(case, positions=()), ends, noise_v_rms, spec)
            cur_scn = scenario(case, ends, noise_v_rms, spec)
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
                regions[name].extend(region_outcomes(result, case, current.circumference_mm))
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
            hits = regions[name]
            inside = (f"; 90 % regions: truth inside {sum(h for h, _ in hits)}/{len(hits)} detected, median "
                      f"half-width {statistics.median(w for _, w in hits):.1f} mm" if hits else "")
            print(f"- {name}: median {statistics.median(e):.1f} mm, worst {max(e):.1f} mm over {len(e)} positions; "
                  f"median {statistics.median(times[name]):.0f} ms per assessment{inside}")
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


def modes_campaign(n: int, seed: int, spread_c: float = 3.0) -> None:
    """Defect-free leaky records (n per ring and end condition), noise, 20 +- ``spread_c`` degC, one 20 degC baseline."""
    rng = np.random.default_rng(seed)
    print(f"\n### False alarms with leakage: {n} defect-free records per row, noise, 20 +- {spread_c:g} degC, "
          "one 20 degC baseline\n")
    print("| ring | ends | threshold | false alarms | peak DI mean | peak DI max | mean + 3.09 sd (1e-3) |")
    print("|---|---|---|---|---|---|---|")
    settings = replace(METHODS["multipath"], max_defects=1)
    for n_tx, case in ((16, PAPER_CASES[0]), (8, PAPER_CASES[6])):
        for ends in ("reflecting", "absorbing"):
            clean = replace(case, positions=())
            scn = scenario(clean, ends, NOISE_V_RMS, leaky(clean, convert=False))
            baseline = record(scn, 20.0, rng)
            peaks = []
            for _ in range(n):
                current = record(scn, 20.0 + rng.uniform(-spread_c, spread_c), rng)
                result = assess(current, [baseline], settings)
                peaks.append(result.peak_di if result.valid_baseline else np.nan)
            values = np.asarray(peaks)
            thr = settings.effective_threshold
            cal = calibrate_threshold(values[np.isfinite(values)], false_alarm_rate=1e-3)
            print(f"| {n_tx} | {ends} | {thr:.3g} | {int(np.sum(values >= thr))} / {n} "
                  f"({int(np.sum(~np.isfinite(values)))} abstained) | {np.nanmean(values):.3g} | "
                  f"{np.nanmax(values):.3g} | {cal.threshold:.3g} |")


def run_modes(campaign_n: int) -> None:
    """The paper's cases with the other guided modes on (multipath, the default method, only)."""
    ends = ("reflecting", "absorbing")
    default = {"multipath": METHODS["multipath"]}
    print("\n## Other guided modes (leakage at the 8/16-ring levels of LEAKS; conversion as CONVERSIONS)")
    run_condition("Leakage, noise, same temperature", PAPER_CASES, ends, NOISE_V_RMS, 0.0, default, 6,
                  modes=lambda c: leaky(c, convert=False))
    run_condition("Leakage, noise, current +3 degC, with compensation", PAPER_CASES, ends, NOISE_V_RMS, 3.0, default,
                  7, modes=lambda c: leaky(c, convert=False))
    run_condition("Leakage and mode conversion, noise, same temperature", PAPER_CASES, ends, NOISE_V_RMS, 0.0,
                  default, 8, modes=lambda c: leaky(c, convert=True))
    run_condition("Leakage and mode conversion, noise, current +3 degC, with compensation", PAPER_CASES, ends,
                  NOISE_V_RMS, 3.0, default, 9, modes=lambda c: leaky(c, convert=True))
    run_condition("Leakage and mode conversion, noise, current -3 degC, with compensation", PAPER_CASES, ends,
                  NOISE_V_RMS, -3.0, default, 10, modes=lambda c: leaky(c, convert=True))
    run_condition("Two notches, leakage and mode conversion, noise, same temperature", [TWO_NOTCHES], ends,
                  NOISE_V_RMS, 0.0, default, 11, modes=lambda c: leaky(c, convert=True))
    for scale in (2.0, 4.0):
        run_condition(f"Leakage and {scale:g}x stronger mode conversion, noise, current +3 degC, with compensation",
                      PAPER_CASES, ends, NOISE_V_RMS, 3.0, default, 20, modes=lambda c, s=scale: leaky(c, True, s))
    if campaign_n > 0:
        modes_campaign(campaign_n, 12)


def run_modal_filter() -> None:
    """The opt-in modal filter (AssessSettings.modal_orders="auto") against the default, same records."""
    ends = ("reflecting", "absorbing")
    both = {"multipath": METHODS["multipath"], "multipath/modal": replace(METHODS["multipath"], modal_orders="auto")}
    print("\n## Opt-in modal filter (orders 0..1 removed for 16 receivers, 0 for 8; imaging/modal.py)")
    run_condition("Noise, current +3 degC, with compensation", PAPER_CASES, ends, NOISE_V_RMS, 3.0, both, 2)
    run_condition("Noise, current +3 degC, without compensation", PAPER_CASES, ends, NOISE_V_RMS, 3.0,
                  {n: replace(s, compensate=False) for n, s in both.items()}, 2)
    run_condition("Two notches at once (noise, same temperature)", [TWO_NOTCHES], ends, NOISE_V_RMS, 0.0, both, 3)
    run_condition("Leakage and mode conversion, noise, current +3 degC, with compensation", PAPER_CASES, ends,
                  NOISE_V_RMS, 3.0, both, 9, modes=lambda c: leaky(c, convert=True))
    run_condition("Leakage and 4x stronger mode conversion, noise, current +3 degC, with compensation",
                  PAPER_CASES, ends, NOISE_V_RMS, 3.0, both, 20, modes=lambda c: leaky(c, True, 4.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=int, default=500, help="defect-free records per end condition (x2)")
    parser.add_argument("--skip-features", action="store_true", help="skip the feature comparison")
    parser.add_argument("--modes-campaign", type=int, default=250,
                        help="defect-free leaky records per ring and end condition (x4)")
    parser.add_argument("--only-modes", action="store_true", help="run only the other-guided-modes section")
    args = parser.parse_args()
    ends = ("reflecting", "absorbing")
    start = time.perf_counter()
    if args.only_modes:
        run_modes(args.modes_campaign)
        run_modal_filter()
        print(f"\n<!-- total {time.perf_counter() - start:.0f} s -->")
        return
    run_condition("Clean (no receiver noise, same temperature)", PAPER_CASES, ends, 0.0, 0.0, METHODS, 1)
    run_condition("Noise, current +3 degC, with compensation (OBS + BSS)", PAPER_CASES, ends, NOISE_V_RMS, 3.0,
                  METHODS, 2)
    uncompensated = {n: replace(s, compensate=False) for n, s in METHODS.items()}
    run_condition("Noise, current +3 degC, without compensation", PAPER_CASES, ends, NOISE_V_RMS, 3.0,
                  uncompensated, 2)
    run_condition("Two notches at once (noise, same temperature)", [TWO_NOTCHES], ends, NOISE_V_RMS, 0.0, METHODS, 3)
    combined = {"multipath": METHODS["multipath"],
                "groups' powers added": replace(METHODS["multipath"], joint_groups=False)}
    run_condition("Off a receiver's angle (noise, current +3 degC, with compensation)", OFF_RECEIVER_CASES, ends,
                  NOISE_V_RMS, 3.0, combined, 7)
    if not args.skip_features:
        features = {f"multipath/{f}": settings_for("multipath", f) for f in ("analytic", "envelope", "squared")}
        run_condition("Features compared (noise, same temperature)", PAPER_CASES, ends, NOISE_V_RMS, 0.0, features, 4)
    if args.campaign > 0:
        campaign(args.campaign, 5)
    run_modes(args.modes_campaign)
    run_modal_filter()
    print(f"\n<!-- total {time.perf_counter() - start:.0f} s -->")


if __name__ == "__main__":
    main()
