"""What one ``pipesentry analyze`` costs: time and peak memory of the 1 mm x 1 deg map of a record.

Runs ``imaging.analysis.analyze`` (what ``pipesentry analyze`` runs, the file's wall thickness) on one
baseline/current pair of the full-wave development set twice in this process: the first call builds
the grid's gather tables and the per-pixel Gram whitening of the joint map (imaging/multipath.py), the
second finds them cached. Prints both times, the process's peak resident memory before and after, and
what the caches hold. Default record: ``n16_reflecting_notch_150_30`` (16 transducers, end echoes: 18
coherence groups, the largest Grams of the set).

    .venv/bin/python bench/bench_analyze.py [--dev DIR] [--case NAME]

The dev set is not in the repository: without it the benchmark says so and exits 0, except under
CI=true (exit 1). One thread (the figures are per core).
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from imaging import gather, multipath  # noqa: E402
from imaging.analysis import analyze  # noqa: E402
from imaging.formats import load_measurement  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DEFAULT_DEV = REPO.parent / "shared" / "fullwave-dev"
DEFAULT_CASE = "n16_reflecting_notch_150_30"


def peak_rss_gb() -> float:
    """This process's peak resident set so far (Linux reports kilobytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dev", type=Path, default=DEFAULT_DEV, help=f"dev set (default {DEFAULT_DEV})")
    parser.add_argument("--case", default=DEFAULT_CASE, help=f"the case's file stem (default {DEFAULT_CASE})")
    args = parser.parse_args()
    baseline_file = args.dev / f"{args.case}_baseline.npz"
    current_file = args.dev / f"{args.case}_current.npz"
    if not (baseline_file.is_file() and current_file.is_file()):
        print(f"bench_analyze: {baseline_file} or its current is missing (the dev set lives beside the checkout)")
        return 1 if os.environ.get("CI") == "true" else 0
    baseline, current = load_measurement(baseline_file), load_measurement(current_file)
    before = peak_rss_gb()
    times = []
    for _ in range(2):
        start = time.perf_counter()
        result = analyze(baseline, current, wall_mm=current.wall_mm)
        times.append(time.perf_counter() - start)
    tables = list(multipath._tables.values())
    whitenings = multipath._gram_whitening_total.cache
    print(f"analyze() of {args.case}, 1 mm x 1 deg, one thread, numba kernels: "
          f"{'yes' if gather.compiled() else 'no (numpy fallback)'}")
    print(f"  first call (gather tables, Gram whitening built): {times[0]:7.2f} s")
    print(f"  second call (both cached)                     : {times[1]:7.2f} s")
    print(f"  peak RSS: {before:.2f} GB before, {peak_rss_gb():.2f} GB after")
    print(f"  cached: {len(tables)} gather tables, {sum(t.nbytes for t in tables) / 1e6:.0f} MB; "
          f"{len(whitenings)} Gram whitenings, {whitenings.currsize / 1e6:.0f} MB")
    print("  reported: " + ("; ".join(f"{d.axial_mm:.1f} mm {d.angle_deg:.1f} deg (DI {d.di:.3f})"
                                      for d in result.defects) or "nothing"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
