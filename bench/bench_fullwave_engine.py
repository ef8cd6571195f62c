"""Full-wave engine speed: one record of the paper's pipe per model, grid and end condition.

A record is the paper's pipe (1000 x 347.5 mm mid-wall, 16 transducers, 85 kHz, a notch),
600 us at 10 MHz. Target (docs/fullwave.md): seconds to tens of seconds per record on one core.
Also prints the throughput (cell updates per second) and the compiled kernels' speed-up over
their numpy reference on a small grid (both from the same inputs, in this run).

    .venv/bin/python bench/bench_fullwave_engine.py [--repeat 3] [--skip-fine]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")  # one core, as the target says

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from fullwave import inplane, sh  # noqa: E402
from fullwave.defects import Notch  # noqa: E402
from fullwave.dispersion import stable_dt_s  # noqa: E402
from fullwave.record import PipeModel, SimulationSpec, build_grid, simulate  # noqa: E402
from fullwave.transducers import RingLayout  # noqa: E402

NOTCH = (Notch(axial_mm=200.0, angle_deg=90.0),)


def _steps(spec: SimulationSpec) -> tuple[int, int]:
    """(cells, time steps) of a spec's run, as record.simulate_velocities chooses them."""
    grid = build_grid(spec)
    c = spec.pipe.steel.plate_velocity_m_s if spec.model == "inplane" else spec.pipe.steel.shear_velocity_m_s
    dt = stable_dt_s(grid.dz_m, grid.ds_m, c, spec.courant)
    return grid.nz * grid.ns, int(np.ceil(spec.n_samples / spec.fs_hz / dt)) + 4


def _time(spec: SimulationSpec, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        simulate(spec)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def _fallback_ratio(model: str) -> tuple[float, float]:
    """(compiled s, numpy s) for the same 200 x 100 mm, 200 us run."""
    spec = SimulationSpec(pipe=PipeModel(length_mm=200.0, circumference_mm=100.0),
                          rings=RingLayout(tx_axial_mm=20.0, tx_rx_distance_mm=150.0, n_transducers=4),
                          model=model, n_samples=2000)  # type: ignore[arg-type]
    module = inplane if model == "inplane" else sh
    compiled_s = _time(spec, 1)
    kernel = module._run_compiled
    module._run_compiled = None
    try:
        numpy_s = _time(spec, 1)
    finally:
        module._run_compiled = kernel
    return compiled_s, numpy_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per 1 mm row (median)")
    parser.add_argument("--skip-fine", action="store_true", help="leave out the 0.5 mm rows (~1 min each)")
    args = parser.parse_args()
    rows = [("sh", "reflecting", 1.0), ("sh", "absorbing", 1.0), ("inplane", "reflecting", 1.0)]
    if not args.skip_fine:
        rows += [("sh", "reflecting", 0.5), ("sh", "absorbing", 0.5), ("inplane", "reflecting", 0.5)]
    simulate(SimulationSpec(n_samples=50))  # compile (or load) the kernels before timing
    simulate(SimulationSpec(n_samples=50, model="inplane"))
    print(f"load average at start: {os.getloadavg()[0]:.1f}\n")
    print("| model | ends | cell | cells x steps | median per record | cell updates / s |")
    print("|---|---|---|---|---|---|")
    for model, ends, cell in rows:
        spec = SimulationSpec(pipe=PipeModel(ends=ends), defects=NOTCH, model=model, cell_mm=cell)  # type: ignore[arg-type]
        cells, steps = _steps(spec)
        seconds = _time(spec, args.repeat if cell >= 1.0 else 1)
        print(f"| {model} | {ends} | {cell:g} mm | {cells:,} x {steps:,} | {seconds:.2f} s | {cells * steps / seconds:.2e} |")
    print("\n| kernel | compiled | numpy reference | speed-up |")
    print("|---|---|---|---|")
    for model in ("sh", "inplane"):
        compiled_s, numpy_s = _fallback_ratio(model)
        print(f"| {model}, 200 x 100 mm, 1 mm, 200 us | {compiled_s:.2f} s | {numpy_s:.2f} s | {numpy_s / compiled_s:.1f}x |")
    print(f"\nload average at end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
