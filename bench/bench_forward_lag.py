"""A sparse ring's defect placed by its echoes with a forward phase lag fitted beside its axial position.

A notch scatters with a phase that lags by b (1 - cos psi), psi the scattering angle between the
incident wave and the way to the receiver (bench/bench_scatter_phase.py measures b on a 16-ring;
docs/accuracy.md). With a plane incident wave (16 transducers) and no end echoes that lag trades
exactly against the axial position (docs/imaging.md, "A pattern by defect kind"). A ring of 8
elements launches a wave whose direction at the defect differs from element to element, so psi
differs between element-receiver pairs that the axial position moves alike: the trade-off may
break. This benchmark tests that, outside the pipeline, at each case's true angle: the six-leg
echo fit with the first-order pattern (what ``imaging.multidefect`` places a sparse ring's defect
with), each path's burst delayed in phase by b (1 - cos psi) (``fit_smooth_echoes`` ``lags_rad``)
for b in B_GRID_RAD, on an axial grid
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
import statistics  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_fullwave  # noqa: E402

from imaging import pipeline  # noqa: E402
from imaging.analysis import analyze  # noqa: E402
from imaging.echofit import fit_smooth_echoes  # noqa: E402
from imaging.multidefect import FIT_WRAPS, PATTERN_ORDERS  # noqa: E402
from imaging.scene import Scene  # noqa: E402

B_GRID_RAD = (-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0)
AXIAL_SPAN_MM = 40.0
AXIAL_STEP_MM = 2.0


def unexplained(residual: np.ndarray, scene: Scene, z_mm: float, angle_deg: float, lag_rad: float) -> float:
    """The fraction of ``residual`` the six-leg, first-order-pattern fit of one point leaves, its
    echoes lagging by ``lag_rad`` (1 - cos psi) (``imaging.echofit.fit_smooth_echoes``)."""
    fitted = fit_smooth_echoes(residual, scene, [(z_mm, angle_deg)], orders=PATTERN_ORDERS, lags_rad=[lag_rad])[0]
    left = residual - fitted
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
