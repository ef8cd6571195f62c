"""The map's groups added in power against their joint projection: the axial bias of overlapping ways round.

Until 2026-12-05 the coherent map (imaging/multipath.py) scored a pixel as the sum over coherence
groups (a path family and one way round the pipe) of each group's matched-filter power, as if the
groups' templates were orthogonal (``joint_groups=False`` still does). On a receiver near the
scatterer's far side the two ways round arrive within a burst of each other, so they are not: the
sum then counts their overlap twice, and where the axial lobe is broad (no end echoes, little
1 - cos psi across the ring) that moves the peak.
The generalised likelihood ratio with one free complex amplitude per group is the energy of the
record's projection onto the groups' templates jointly: DI^2 = b^H M^-1 b / G, b the groups' sums
(as before), M their cross-Gram (sum over receivers and pairs of paths of w_p w_q C(k_q - k_p), C the
matched feature's complex autocorrelation); noise alone still scores the same (E b b^H = sigma^2 M).

This benchmark computes both (the joint one is ``AssessSettings(joint_groups=True)``, the default
since 2026-12-05; the power sum is ``joint_groups=False``) on an isotropic point scatterer of the
map's own model (tests/support/synthetic.py: direct paths both ways round, no end echoes, noise
5e-4) at several positions, and prints each map's axial error along the scatterer's line (1 mm
steps), then what ``assess`` reports with each. ``--lag RAD ...`` repeats the line peaks with each echo's carrier lagging
by b (1 - cos psi) (a finite scatterer's phase pattern, as the full-wave notch's, docs/accuracy.md;
b / k is where a map without overlap would put the point); ``--taper P ...`` with each echo's
amplitude scaled by cos(psi)^P instead (a pattern without phase law). ``--mock`` prints ``assess``'s
axial offset on mock-node notches and masses (absorbing ends, no noise) with 15 and 0.5 mm
transducers; ``--mock-angles`` the mock's notches and masses on and between receivers' angles.
``--fullwave NAME ...`` also scores dev-set cases.

    .venv/bin/python bench/bench_group_overlap.py [--lag 1.28 2.56] [--taper 2] [--mock] [--mock-angles]
        [--fullwave n16_absorbing_notch_150_30 ...]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from imaging.features import residual_feature  # noqa: E402
from imaging.formats import load_measurement  # noqa: E402
from imaging.grid import Grid  # noqa: E402
from imaging.multipath import local_multipath_pixels, path_model_for  # noqa: E402
from imaging.pipeline import AssessSettings, assess  # noqa: E402
from imaging.scene import Scene  # noqa: E402
from imaging.timing import MM_PER_M, surface_distance_mm  # noqa: E402
from tests.support.synthetic import C_M_S, baseline_and_scatterers  # noqa: E402

POSITIONS = [(50.0, 100.0), (80.0, 10.0), (150.0, 60.0), (250.0, 200.0), (320.0, 100.0), (370.0, 300.0)]
DEV = REPO.parent / "shared" / "fullwave-dev"


def line_peak(joint: bool, baseline, current, axial_mm: float, angle_deg: float) -> float:
    """The map's peak along the scatterer's line, +-40 mm at 1 mm, as an axial offset from the truth."""
    scene = Scene.of(baseline, path_model_for(baseline), Grid(axial_mm - 40.0, 1.0, 81, angle_deg, 1.0, 1),
                     joint_groups=joint)
    residual = current.traces.astype(np.float64) - baseline.traces.astype(np.float64)
    profile = local_multipath_pixels(residual_feature(residual, scene), scene)[:, 0]
    return float(np.argmax(profile)) - 40.0


def mock_offsets() -> None:
    """``assess``'s axial offset on mock records (T(0,1) only, no noise, absorbing ends), both maps."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_accuracy import METHODS, PAPER_CASES, record, scenario

    print("\nmock node, absorbing ends, no noise: assess's axial offset, power / joint (mm)")
    for length_mm in (15.0, 0.5):
        for case in (PAPER_CASES[0], PAPER_CASES[1], PAPER_CASES[6], PAPER_CASES[7]):
            rng = np.random.default_rng(3)

            def node(c, length_mm=length_mm):
                scn = scenario(c, "absorbing", 0.0)
                rings = scn.rings.model_copy(update={"transducer_length_mm": length_mm, "transducer_width_mm": length_mm})
                return scn.model_copy(update={"rings": rings})

            base = record(node(dataclasses.replace(case, positions=())), 20.0, rng)
            cur = record(node(case), 20.0, rng)
            offsets = []
            for joint in (False, True):
                result = assess(cur, [base], dataclasses.replace(METHODS["multipath"], joint_groups=joint))
                found = result.defects[0] if result.defects else result.peak
                offsets.append(found.axial_mm - case.positions[0][0])
            print(f"  {length_mm:4.1f} mm transducers, {case.name}: {offsets[0]:+.1f} / {offsets[1]:+.1f}")


def mock_angles() -> None:
    """``assess``'s error on mock records (T(0,1) only, no noise) with the defect on a receiver's
    angle and between two, both maps: bench_accuracy.py's cases all lie on a receiver's angle."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_accuracy import METHODS, Case, record, scenario

    print("\nmock node, no noise: assess's error, power / joint (mm), by angle off the nearest receiver")
    for kind, n_rx, hz in (("notch", 16, 85e3), ("mass", 8, 75e3)):
        pitch = 360.0 / n_rx
        for ends in ("absorbing", "reflecting"):
            errors: dict[bool, list[float]] = {False: [], True: []}
            for z in (100.0, 200.0, 300.0):
                cells = []
                for off in (0.0, pitch / 4, pitch / 2):
                    angle = 2 * pitch + off
                    case = Case(kind, kind, ((z, angle),), n_rx, hz)
                    rng = np.random.default_rng(3)
                    base = record(scenario(dataclasses.replace(case, positions=()), ends, 0.0), 20.0, rng)
                    cur = record(scenario(case, ends, 0.0), 20.0, rng)
                    pair = []
                    for joint in (False, True):
                        result = assess(cur, [base], dataclasses.replace(METHODS["multipath"], joint_groups=joint))
                        found = [(d.axial_mm, d.angle_deg) for d in result.defects] or [
                            (result.peak.axial_mm, result.peak.angle_deg)]
                        error = min(surface_distance_mm(e[0], e[1], z, angle, cur.circumference_mm) for e in found)
                        errors[joint].append(error)
                        pair.append(error)
                    cells.append(f"{off:5.2f} deg {pair[0]:5.1f} / {pair[1]:5.1f}")
                print(f"  {kind} {n_rx} rx {ends:10s} {z:3.0f} mm: " + "; ".join(cells))
            print(f"  {kind} {ends}: median {np.median(errors[False]):.1f} / {np.median(errors[True]):.1f}, "
                  f"worst {max(errors[False]):.1f} / {max(errors[True]):.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fullwave", nargs="*", default=[], metavar="NAME", help="dev-set cases to score too")
    parser.add_argument("--lag", nargs="*", type=float, default=[], metavar="RAD",
                        help="forward phase lags b to repeat the line peaks with")
    parser.add_argument("--taper", nargs="*", type=float, default=[], metavar="P",
                        help="amplitude patterns cos(psi)^P to repeat the line peaks with")
    parser.add_argument("--mock", action="store_true",
                        help="also the mock node's notches and masses (absorbing ends), 15 and 0.5 mm transducers")
    parser.add_argument("--mock-angles", action="store_true",
                        help="the mock node's notches and masses on and between receiver angles, both ends")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    print("isotropic point, direct paths both ways round, no end echoes (the map's own model)")
    print(f"{'z / deg':>12} {'line peak: power / joint (mm)':>30} {'assess error: power / joint (mm)':>34} "
          f"{'DI power / joint':>18}")
    for z, a in POSITIONS:
        base, cur = baseline_and_scatterers([(z, a, 0.05)], noise_rms=5e-4, seed=2)
        power_line = line_peak(False, base, cur, z, a)
        joint_line = line_peak(True, base, cur, z, a)
        plain = assess(cur, [base], AssessSettings()).defects[0]
        joint = assess(cur, [base], AssessSettings(joint_groups=True)).defects[0]
        errors = [surface_distance_mm(d.axial_mm, d.angle_deg, z, a, base.circumference_mm) for d in (plain, joint)]
        print(f"{z:5.0f} / {a:4.0f} {power_line:+14.0f} / {joint_line:+4.0f}      {errors[0]:16.1f} / {errors[1]:4.1f}"
              f"      {plain.di:.4f} / {joint.di:.4f}")
    for lag in args.lag:
        k_per_mm = 2 * np.pi * 85e3 / (C_M_S * MM_PER_M)  # the synthetic echoes' carrier (85 kHz) and speed
        print(f"\nforward phase lag b = {lag:g} rad (b / k = {lag / k_per_mm:.1f} mm): line peak, power / joint (mm)")
        for z, a in POSITIONS:
            base, cur = baseline_and_scatterers([(z, a, 0.05)], noise_rms=5e-4, seed=2, forward_lag_rad=lag)
            print(f"{z:5.0f} / {a:4.0f} {line_peak(False, base, cur, z, a):+8.0f} / "
                  f"{line_peak(True, base, cur, z, a):+4.0f}")
    for power in args.taper:
        print(f"\namplitude pattern cos(psi)^{power:g}, no phase law: line peak, power / joint (mm)")
        for z, a in POSITIONS:
            base, cur = baseline_and_scatterers([(z, a, 0.05)], noise_rms=5e-4, seed=2, taper_power=power)
            print(f"{z:5.0f} / {a:4.0f} {line_peak(False, base, cur, z, a):+8.0f} / "
                  f"{line_peak(True, base, cur, z, a):+4.0f}")
    if args.mock:
        mock_offsets()
    if args.mock_angles:
        mock_angles()
    if args.fullwave:
        manifest = {c["case"]: c for c in json.loads((DEV / "manifest.json").read_text())["cases"]}
        print("\ndev-set cases (assess error to each true defect, mm: power / joint)")
        for name in args.fullwave:
            entry = manifest[name]
            base, cur = load_measurement(DEV / entry["baseline"]), load_measurement(DEV / entry["current"])
            results = [assess(cur, [base], AssessSettings(joint_groups=joint)) for joint in (False, True)]
            cells = []
            for d in entry["defects"]:
                z, a = float(d["axial_mm"]), float(d["angle_deg"])
                errs = [min((surface_distance_mm(x.axial_mm, x.angle_deg, z, a, cur.circumference_mm)
                             for x in r.defects), default=float("nan")) for r in results]
                cells.append(f"{errs[0]:.1f} / {errs[1]:.1f}")
            print(f"  {name}: {'; '.join(cells)}; reported {len(results[0].defects)} / {len(results[1].defects)}")
    print(f"({time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
