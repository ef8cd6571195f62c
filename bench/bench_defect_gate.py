"""The second-defect gate (imaging/multidefect.py MIN_RELATIVE_DI): spurious extra defects on
single-defect records against two-defect recall, for several gate values, on the mock physics.

    .venv/bin/python bench/bench_defect_gate.py [--gates 0.3 0.2 0.15]

Records (default receiver noise, 16 transducers at 85 kHz for notches, 8 at 75 kHz for masses):
the benchmark's paper cases with one defect, T(0,1) only (both ends, 0 and +3 degC) and with
mode conversion at the defect (docs/accuracy.md's assumed levels, 1x and 2x, 0 and +-3 degC);
two notches at 4 position pairs, both ends, the second notch equal or 1 mm deep. A gate value is
set on the module for the run (it is a module constant, read at each search).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import METHODS, PAPER_CASES, leaky, record, scenario

import imaging.multidefect as multidefect
from imaging.pipeline import assess
from imaging.timing import surface_distance_mm
from mocknode.scenario import (
    AcquisitionSpec,
    DefectSpec,
    ExcitationSpec,
    ModesSpec,
    NodeScenario,
    NotchSize,
    PipeSpec,
    RingSpec,
)

NOISE = AcquisitionSpec().noise_v_rms
PAIRS = [((150.0, 45.0), (300.0, 225.0)), ((100.0, 90.0), (300.0, 270.0)), ((200.0, 0.0), (250.0, 180.0)),
         ((120.0, 300.0), (280.0, 60.0))]
FOUND_MM = 30.0  # a true defect counts as found with an estimate this close


def spurious(conditions, seed: int) -> tuple[int, int]:
    """Extra defects reported on single-defect records, and how many records were imaged."""
    rng = np.random.default_rng(seed)
    extra = n = 0
    for ends, delta_c, modes in conditions:
        for case in PAPER_CASES:
            spec = modes(case) if modes else None
            baseline = record(scenario(replace(case, positions=()), ends, NOISE, spec), 20.0, rng)
            current = record(scenario(case, ends, NOISE, spec), 20.0 + delta_c, rng)
            result = assess(current, [baseline], METHODS["multipath"])
            if result.valid_baseline:
                n += 1
                extra += max(0, len(result.defects) - 1)
    return extra, n


def two_notches(pair, second_depth_mm: float | None, ends: str) -> tuple[NodeScenario, NodeScenario]:
    base = NodeScenario(node_id="bench", pipe=PipeSpec(ends=ends, wall_mm=4.0), rings=RingSpec(n_transducers=16),
                        excitation=ExcitationSpec(frequency_hz=85e3), acquisition=AcquisitionSpec(noise_v_rms=NOISE),
                        modes=ModesSpec())
    second = NotchSize(depth_mm=second_depth_mm) if second_depth_mm else NotchSize()
    defects = [DefectSpec(kind="notch", axial_mm=pair[0][0], angle_deg=pair[0][1]),
               DefectSpec(kind="notch", axial_mm=pair[1][0], angle_deg=pair[1][1], size=second)]
    return base, NodeScenario.model_validate({**base.model_dump(), "defects": [d.model_dump() for d in defects]})


def recall(seed: int) -> tuple[int, int, list[float], int]:
    rng = np.random.default_rng(seed)
    found, total, errors, far = 0, 0, [], 0
    for ends in ("reflecting", "absorbing"):
        for depth in (None, 1.0):
            for pair in PAIRS:
                base_scn, cur_scn = two_notches(pair, depth, ends)
                baseline, current = record(base_scn, 20.0, rng), record(cur_scn, 20.0, rng)
                result = assess(current, [baseline], METHODS["multipath"])
                estimates = [(d.axial_mm, d.angle_deg) for d in result.defects]
                per_truth = [min([surface_distance_mm(e[0], e[1], z, a, current.circumference_mm) for e in estimates]
                                 or [float("inf")]) for z, a in pair]
                hits = [e for e in per_truth if e <= FOUND_MM]
                found, total, errors = found + len(hits), total + 2, errors + hits
                far += max(0, len(estimates) - len(hits))
    return found, total, errors, far


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gates", type=float, nargs="+", default=[0.3, 0.2, 0.15])
    args = parser.parse_args()
    plain = [(ends, dc, None) for ends in ("reflecting", "absorbing") for dc in (0.0, 3.0)]
    converting = [(ends, dc, (lambda case, s=scale: leaky(case, True, s)))
                  for scale in (1.0, 2.0) for ends in ("reflecting", "absorbing") for dc in (0.0, 3.0, -3.0)]
    print("| gate | spurious, T(0,1) only | spurious, with mode conversion | two notches found (<= 30 mm) | "
          "median error mm | estimates far from any notch |")
    print("|---|---|---|---|---|---|")
    for gate in args.gates:
        multidefect.MIN_RELATIVE_DI = gate
        s_plain, n_plain = spurious(plain, seed=7)
        s_conv, n_conv = spurious(converting, seed=11)
        found, total, errors, far = recall(seed=13)
        print(f"| {gate:g} | {s_plain} of {n_plain} records | {s_conv} of {n_conv} records | {found} of {total} | "
              f"{statistics.median(errors):.1f} | {far} |", flush=True)


if __name__ == "__main__":
    main()
