"""Imaging benchmark: Algorithm 1 as printed vs the production gather, same inputs, one run.

16 receivers x 6000 samples at 10 MHz over the default 401 x 360 grid. Prints both medians
and their ratio. Targets (docs/benchmarks.md): production median <= 10 ms on one core,
>= 300x faster than the literal version.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")  # one core, as the target says

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from imaging.dimap import compute_di_map, literal_di_map  # noqa: E402
from imaging.measurement import Measurement  # noqa: E402


def inputs(n_rx: int = 16, n_samples: int = 6000, seed: int = 1) -> tuple[Measurement, Measurement]:
    rng = np.random.default_rng(seed)
    angles = np.arange(n_rx) * 360.0 / n_rx
    t = np.arange(n_samples) / 10e6
    pulse_t = t - 400.0 / 3.13e6
    direct = np.where((pulse_t >= 0) & (pulse_t <= 5 / 85e3),
                      0.5 * (1 - np.cos(2 * np.pi * 85e3 * pulse_t / 5)) * np.sin(2 * np.pi * 85e3 * pulse_t), 0.0)
    base = np.tile(direct, (n_rx, 1)) + rng.normal(0, 1e-3, (n_rx, n_samples))
    cur = base + rng.normal(0, 1e-2, (n_rx, n_samples))

    def meas(traces):
        return Measurement(traces.astype(np.float32), 10e6, 0.0, angles, angles, 400.0, 114.6 * np.pi)

    return meas(base), meas(cur)


def median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--literal-repeats", type=int, default=3)
    parser.add_argument("--fast-repeats", type=int, default=50)
    args = parser.parse_args()
    base, cur = inputs()
    first = time.perf_counter()
    fast_map = compute_di_map(base, cur)  # builds and caches the geometry's index table
    cold_ms = (time.perf_counter() - first) * 1e3
    fast = median_s(lambda: compute_di_map(base, cur), args.fast_repeats)
    literal = median_s(lambda: literal_di_map(base, cur), args.literal_repeats)
    agree = float(np.max(np.abs(fast_map.pixels - literal_di_map(base, cur)) / literal_di_map(base, cur).max()))
    print("imaging benchmark: 16 rx x 6000 samples @ 10 MHz, grid 401 x 360, one thread")
    print(f"  production (cached table) median: {fast * 1e3:8.2f} ms   (first call incl. table: {cold_ms:.1f} ms)")
    print(f"  literal Algorithm 1 median      : {literal * 1e3:8.0f} ms")
    print(f"  speed-up                        : {literal / fast:8.0f} x")
    print(f"  max |fast - literal| / max      : {agree:.1e}")
    print(f"  targets: production <= 10 ms: {'met' if fast <= 0.010 else 'MISSED'}; "
          f">= 300x: {'met' if literal / fast >= 300 else 'MISSED'}")


if __name__ == "__main__":
    main()
