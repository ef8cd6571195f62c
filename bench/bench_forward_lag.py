"""A sparse ring's defect placed by its echoes with a forward phase lag fitted beside its axial position.

A notch scatters with a phase that lags by b (1 - cos psi), psi the scattering angle between the
incident wave and the way to the receiver (bench/bench_scatter_phase.py measures b on a 16-ring;
docs/accuracy.md). With a plane incident wave (16 transducers) and no end echoes that lag trades
exactly against the axial position (docs/imaging.md, "A pattern by defect kind"). A ring of 8
elements launches a wave whose direction at the defect differs from element to element, so psi
differs between element-receiver pairs that the axial position moves alike: the trade-off may
break. This benchmark tests that, outside the pipeline, at each case's true angle: the six-leg
echo fit with the first-order pattern (what ``imaging.multidefect`` places a sparse ring's defect
with), each path's burst delayed in phase by b (1 - cos psi) for b in B_GRID_RAD, on an axial grid
of AXIAL_STEP_MM within AXIAL_SPAN_MM of the truth; it prints per case the axial position that
leaves least with b = 0 (today's fit) and with the best b, and the best z for every b.

    .venv/bin/python bench/bench_forward_lag.py PATTERN DIR [DIR ...]

PATTERN: the cases' names (shell pattern); DIR: sets in the dev set's layout (``../shared/fullwave-dev``,
a ``python -m fullwave generate --held-out`` draw) or the own set (a directory named ``*own*``).
Only single-defect cases on rings modelled by elements are scored. ~20 s a case on one core.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import fnmatch  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import fft as sp_fft  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_fullwave  # noqa: E402

from imaging import pipeline  # noqa: E402
from imaging.analysis import analyze  # noqa: E402
from imaging.echofit import FIT_RCOND, _bearing_basis, burst_pair  # noqa: E402
from imaging.multidefect import FIT_WRAPS, PATTERN_ORDERS  # noqa: E402
from imaging.paths import NEGLIGIBLE_WEIGHT, coherence_groups, path_weight, signed_arc_mm, wrap_offsets_mm  # noqa: E402
from imaging.scene import Scene  # noqa: E402
from imaging.timing import MM_PER_M  # noqa: E402

B_GRID_RAD = (-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0)
AXIAL_SPAN_MM = 40.0
AXIAL_STEP_MM = 2.0


def element_paths(scene: Scene, z_mm: float, pixel_deg: float, rx_deg: float) -> tuple[np.ndarray, ...]:
    """(group, length mm, weight, cos psi) of every path (family, leg, element image) from the Tx
    elements via the point (``z_mm``, ``pixel_deg``) to the receiver at ``rx_deg``; psi between the
    incident direction at the point (the gradient of the incident length) and the outgoing one."""
    model = scene.model
    circ = model.circumference_mm
    legs = wrap_offsets_mm(np.asarray(signed_arc_mm(pixel_deg - rx_deg, circ)), circ, model.wraps)
    images = np.arange(-model.tx_images, model.tx_images + 1) * circ
    tx = np.repeat(np.asarray(model.tx_arcs_mm, dtype=np.float64), images.size)
    shift = np.tile(images, len(model.tx_arcs_mm))
    rows = []
    for f, family in enumerate(model.families()):
        zeta = family.in_offset_mm + family.in_sign * z_mm
        s = signed_arc_mm((pixel_deg * circ / 360.0 - tx) * 360.0 / circ, circ) + shift
        r_in = np.sqrt(zeta * zeta + s * s)
        w_in = path_weight(circ / len(model.tx_arcs_mm) / model.wavelength_mm, zeta, r_in, model)
        w_in = np.where(w_in < NEGLIGIBLE_WEIGHT, 0.0, w_in)
        dz = family.rx_image_mm - z_mm
        for k, leg in enumerate(legs):
            leg = float(leg)
            r_out = math.hypot(dz, leg)
            w_out = float(path_weight(family.factor, dz, r_out, model))
            cos_psi = (family.in_sign * zeta * dz - s * leg) / (r_in * r_out)
            rows += [(f * model.wraps + k, r_in[e] + r_out, w_in[e] * w_out, cos_psi[e]) for e in range(s.size)]
    table = np.array(rows)
    return table[:, 0].astype(np.int64), table[:, 1], table[:, 2], table[:, 3]


def unexplained(residual: np.ndarray, scene: Scene, z_mm: float, angle_deg: float, lag_rad: float) -> float:
    """The fraction of ``residual`` the six-leg, first-order-pattern fit of one point leaves, its
    echoes lagging by ``lag_rad`` (1 - cos psi)."""
    n_rx, n = residual.shape
    shapes = np.stack(burst_pair(scene.fs_hz, scene.excitation_hz, scene.cycles))
    size = shapes.shape[1]
    impulses = np.zeros((n_rx, coherence_groups(scene.model), 2, n + size))  # in-phase and quadrature parts
    c_mm_s = scene.velocity_m_s * MM_PER_M
    for m in np.flatnonzero(scene.rx_mask):
        group, length, weight, cos_psi = element_paths(scene, z_mm, angle_deg, float(scene.rx_angles_deg[m]))
        k = np.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5).astype(np.int64)
        keep = (k < n) & (k + size > 0) & (weight > 0)
        phase = lag_rad * (1.0 - cos_psi)
        np.add.at(impulses, (m, group[keep], 0, k[keep] + size), (weight * np.cos(phase))[keep])
        np.add.at(impulses, (m, group[keep], 1, k[keep] + size), (weight * np.sin(phase))[keep])
    n_fft = sp_fft.next_fast_len(n + 2 * size, real=True)
    spec = sp_fft.rfft(impulses, n_fft, axis=-1)
    burst, quadrature = sp_fft.rfft(shapes, n_fft, axis=-1)
    # sin(x - phase) = sin x cos phase - cos x sin phase; cos(x - phase) = cos x cos phase + sin x sin phase
    columns = np.stack([spec[:, :, 0] * burst - spec[:, :, 1] * quadrature,
                        spec[:, :, 0] * quadrature + spec[:, :, 1] * burst], axis=2)
    columns = sp_fft.irfft(columns, n_fft, axis=-1)[..., size:size + n].reshape(n_rx, -1, n)
    gram = np.einsum("man,mbn->mab", columns, columns)
    rhs = np.einsum("man,mn->ma", columns, residual)
    basis = np.repeat(_bearing_basis(scene, [(z_mm, angle_deg)], PATTERN_ORDERS), columns.shape[1], axis=1)
    n_basis = basis.shape[-1]
    big = np.einsum("mak,mab,mbl->akbl", basis, gram, basis).reshape(columns.shape[1] * n_basis, -1)
    unknowns = np.linalg.pinv(big, rtol=FIT_RCOND, hermitian=True) @ np.einsum("mak,ma->ak", basis, rhs).ravel()
    coef = np.einsum("mak,ak->ma", basis, unknowns.reshape(columns.shape[1], n_basis))
    left = residual - np.einsum("ma,man->mn", coef, columns)
    return float(np.sum(left * left) / np.sum(residual * residual))


def cases(root: Path):
    return bench_fullwave.own_from_files(root, []) if "own" in root.name else bench_fullwave.dev_cases(root)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pattern")
    parser.add_argument("dirs", nargs="+", type=Path)
    args = parser.parse_args()
    seen: list[tuple[float, float]] = []
    captured: list[tuple] = []
    find_defects = pipeline.find_defects

    def keep(residual, scene, **kwargs):
        found = find_defects(residual, scene, **kwargs)
        captured.append((residual, scene, found))
        return found

    pipeline.find_defects = keep
    for root in args.dirs:
        for entry, baseline, current in cases(root):
            if not fnmatch.fnmatch(entry["case"], args.pattern) or len(entry["defects"]) != 1:
                continue
            captured.clear()
            analyze(baseline, current, wall_mm=current.wall_mm)
            residual, scene, (_, found, _) = captured[-1]
            if not found or not scene.model.elements:
                continue
            scene = dataclasses.replace(scene, model=dataclasses.replace(scene.model, wraps=FIT_WRAPS))
            true_z, true_angle = float(entry["defects"][0]["axial_mm"]), float(entry["defects"][0]["angle_deg"])
            zs = np.arange(max(5.0, true_z - AXIAL_SPAN_MM), min(scene.model.tx_rx_distance_mm - 5.0,
                                                                  true_z + AXIAL_SPAN_MM) + 1e-9, AXIAL_STEP_MM)
            best = {}
            for lag in B_GRID_RAD:
                left = [unexplained(residual, scene, float(z), true_angle, lag) for z in zs]
                best[lag] = (float(zs[int(np.argmin(left))]), min(left))
            lag = min(best, key=lambda b: best[b][1])
            seen.append((abs(best[0.0][0] - true_z), abs(best[lag][0] - true_z)))
            print(f"{entry['case']:44s} truth {true_z:5.1f} mm, reported {found[0].estimate.axial_mm:6.1f} | "
                  f"b = 0: {best[0.0][0]:5.1f} (leaves {best[0.0][1]:.3f}) | best b = {lag:+.0f} rad: "
                  f"{best[lag][0]:5.1f} (leaves {best[lag][1]:.3f}) | z per b: "
                  + " ".join(f"{b:+.0f}:{best[b][0]:.0f}" for b in B_GRID_RAD), flush=True)
    if seen:
        print(f"axial error at the true angle, median over {len(seen)} cases: b = 0 "
              f"{statistics.median(s[0] for s in seen):.1f} mm, best b {statistics.median(s[1] for s in seen):.1f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
