"""The map's groups added in power against their joint projection: the axial bias of overlapping ways round.

The coherent map (imaging/multipath.py) scores a pixel as the sum over coherence groups (a path
family and one way round the pipe) of each group's matched-filter power, as if the groups'
templates were orthogonal. On a receiver near the scatterer's far side the two ways round arrive
within a burst of each other, so they are not: the sum then counts their overlap twice, and where
the axial lobe is broad (no end echoes, little 1 - cos psi across the ring) that moves the peak.
The generalised likelihood ratio with one free complex amplitude per group is the energy of the
record's projection onto the groups' templates jointly: DI^2 = b^H M^-1 b / G, b the groups' sums
(as now), M their cross-Gram (sum over receivers and pairs of paths of w_p w_q C(k_q - k_p), C the
matched feature's complex autocorrelation); noise alone still scores the same (E b b^H = sigma^2 M).

This benchmark computes both, in numpy, on an isotropic point scatterer of the map's own model
(tests/support/synthetic.py: direct paths both ways round, no end echoes, noise 5e-4) at several
positions, and prints each map's axial error along the scatterer's line (1 mm steps), then what
``assess`` reports with each (the joint one patched into the defect search; ~10x slower than the
compiled map, fine here). ``--lag RAD ...`` repeats the line peaks with each echo's carrier lagging
by b (1 - cos psi) (a finite scatterer's phase pattern, as the full-wave notch's, docs/accuracy.md;
b / k is where a map without overlap would put the point); ``--taper P ...`` with each echo's
amplitude scaled by cos(psi)^P instead (a pattern without phase law). ``--mock`` prints ``assess``'s
axial offset on mock-node notches and masses (absorbing ends, no noise) with 15 and 0.5 mm
transducers. ``--fullwave NAME ...`` also scores
dev-set cases (~20 s each with the joint map).

    .venv/bin/python bench/bench_group_overlap.py [--lag 1.28 2.56] [--taper 2] [--mock] [--fullwave n16_absorbing_notch_150_30 ...]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from functools import lru_cache  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import imaging.multidefect as multidefect  # noqa: E402
from imaging.arrivals import analytic_matched, hann_burst  # noqa: E402
from imaging.features import residual_feature  # noqa: E402
from imaging.formats import load_measurement  # noqa: E402
from imaging.grid import Grid  # noqa: E402
from imaging.multipath import local_multipath_pixels, path_model_for  # noqa: E402
from imaging.paths import stacked_paths  # noqa: E402
from imaging.pipeline import AssessSettings, assess  # noqa: E402
from imaging.scene import Scene  # noqa: E402
from imaging.timing import MM_PER_M, surface_distance_mm  # noqa: E402
from tests.support.synthetic import C_M_S, baseline_and_scatterers  # noqa: E402

POSITIONS = [(50.0, 100.0), (80.0, 10.0), (150.0, 60.0), (250.0, 200.0), (320.0, 100.0), (370.0, 300.0)]
DEV = REPO.parent / "shared" / "fullwave-dev"


@lru_cache(maxsize=8)
def complex_correlation(fs_hz: float, excitation_hz: float, cycles: int) -> np.ndarray:
    """C(d) = E[A(k) conj A(k + d)] / E|A|^2 of the analytic matched feature for white noise, d = 0, 1, ..."""
    burst = hann_burst(fs_hz, excitation_hz, cycles)
    size = burst.size
    impulse = np.zeros(4 * size)
    impulse[2 * size] = 1.0
    response = analytic_matched(impulse, burst)
    corr = np.array([np.vdot(response[:response.size - d], response[d:]) for d in range(2 * size)])
    return np.conj(corr / corr[0])


def joint_pixels(feature: np.ndarray, scene: Scene, *, normalise: str = "snr") -> np.ndarray:
    """The map with the groups projected on jointly (module docstring); plane-wave models, complex features."""
    model, grid = scene.model, scene.grid
    corr = complex_correlation(scene.fs_hz, scene.excitation_hz, scene.cycles)
    span = corr.size
    c_mm_s = scene.velocity_m_s * MM_PER_M
    n = feature.shape[1]
    sums: np.ndarray | None = None
    gram: np.ndarray | None = None
    for m in np.flatnonzero(scene.rx_mask):
        rel = grid.angle_deg[None, :] - scene.rx_angles_deg[m]
        _groups, length, weight = stacked_paths(model, grid.axial_mm[:, None], rel, scene.rx_angles_deg[m])
        length, weight = np.broadcast_arrays(length, weight)
        k = np.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5).astype(np.int64)
        inside = (k >= 0) & (k < n)
        w = np.where(inside, weight ** scene.power, 0.0)
        n_paths = w.shape[0]
        if sums is None or gram is None:
            sums = np.zeros((n_paths,) + grid.shape, complex)
            gram = np.zeros(grid.shape + (n_paths, n_paths), complex)
        sums += w * feature[m][np.where(inside, k, 0)]
        for p in range(n_paths):
            gram[..., p, p] += w[p] * w[p]
            for q in range(p + 1, n_paths):
                lag = k[q] - k[p]
                value = np.where(np.abs(lag) < span, corr[np.minimum(np.abs(lag), span - 1)], 0.0)
                term = w[p] * w[q] * np.where(lag >= 0, value, np.conj(value))
                gram[..., p, q] += term
                gram[..., q, p] += np.conj(term)
    assert sums is not None and gram is not None
    b = np.moveaxis(sums, 0, -1)
    quadratic = np.einsum("...i,...ij,...j->...", b.conj(), np.linalg.pinv(gram, rcond=1e-6, hermitian=True), b).real
    snr = np.sqrt(np.maximum(quadratic, 0.0) / b.shape[-1])
    if normalise == "snr":
        return snr
    total = np.trace(gram, axis1=-2, axis2=-1).real
    return np.where(total > 0, snr * np.sqrt(b.shape[-1]) / np.sqrt(np.where(total > 0, total, 1.0)), 0.0)


@contextlib.contextmanager
def joint_map() -> Iterator[None]:
    """The defect search imaging with ``joint_pixels`` (plane-wave models) while inside."""
    saved = multidefect.multipath_pixels, multidefect.local_multipath_pixels

    def full(feature, scene, *, normalise="snr"):
        if scene.model.elements or not np.iscomplexobj(feature):
            return saved[0](feature, scene, normalise=normalise)
        return joint_pixels(np.asarray(feature), scene, normalise=normalise)

    def local(feature, scene, *, normalise="snr", compiled=True):
        if scene.model.elements or not np.iscomplexobj(feature):
            return saved[1](feature, scene, normalise=normalise, compiled=compiled)
        return joint_pixels(np.asarray(feature), scene, normalise=normalise)

    multidefect.multipath_pixels, multidefect.local_multipath_pixels = full, local
    try:
        yield
    finally:
        multidefect.multipath_pixels, multidefect.local_multipath_pixels = saved


def line_peak(image, baseline, current, axial_mm: float, angle_deg: float) -> float:
    """The map's peak along the scatterer's line, +-40 mm at 1 mm, as an axial offset from the truth."""
    scene = Scene.of(baseline, path_model_for(baseline), Grid(axial_mm - 40.0, 1.0, 81, angle_deg, 1.0, 1))
    residual = current.traces.astype(np.float64) - baseline.traces.astype(np.float64)
    profile = image(residual_feature(residual, scene), scene)[:, 0]
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
                with joint_map() if joint else contextlib.nullcontext():
                    result = assess(cur, [base], METHODS["multipath"])
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
                        with joint_map() if joint else contextlib.nullcontext():
                            result = assess(cur, [base], METHODS["multipath"])
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
        power_line = line_peak(local_multipath_pixels, base, cur, z, a)
        joint_line = line_peak(joint_pixels, base, cur, z, a)
        plain = assess(cur, [base], AssessSettings()).defects[0]
        with joint_map():
            joint = assess(cur, [base], AssessSettings()).defects[0]
        errors = [surface_distance_mm(d.axial_mm, d.angle_deg, z, a, base.circumference_mm) for d in (plain, joint)]
        print(f"{z:5.0f} / {a:4.0f} {power_line:+14.0f} / {joint_line:+4.0f}      {errors[0]:16.1f} / {errors[1]:4.1f}"
              f"      {plain.di:.4f} / {joint.di:.4f}")
    for lag in args.lag:
        k_per_mm = 2 * np.pi * 85e3 / (C_M_S * MM_PER_M)  # the synthetic echoes' carrier (85 kHz) and speed
        print(f"\nforward phase lag b = {lag:g} rad (b / k = {lag / k_per_mm:.1f} mm): line peak, power / joint (mm)")
        for z, a in POSITIONS:
            base, cur = baseline_and_scatterers([(z, a, 0.05)], noise_rms=5e-4, seed=2, forward_lag_rad=lag)
            print(f"{z:5.0f} / {a:4.0f} {line_peak(local_multipath_pixels, base, cur, z, a):+8.0f} / "
                  f"{line_peak(joint_pixels, base, cur, z, a):+4.0f}")
    for power in args.taper:
        print(f"\namplitude pattern cos(psi)^{power:g}, no phase law: line peak, power / joint (mm)")
        for z, a in POSITIONS:
            base, cur = baseline_and_scatterers([(z, a, 0.05)], noise_rms=5e-4, seed=2, taper_power=power)
            print(f"{z:5.0f} / {a:4.0f} {line_peak(local_multipath_pixels, base, cur, z, a):+8.0f} / "
                  f"{line_peak(joint_pixels, base, cur, z, a):+4.0f}")
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
            results = [assess(cur, [base], AssessSettings())]
            with joint_map():
                results.append(assess(cur, [base], AssessSettings()))
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
