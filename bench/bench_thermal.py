"""Temperature compensation on two independent physics: the medium's response stretched, the burst not.

A warmer pipe stretches the medium's impulse response, not the node's excitation burst
(imaging/thermal.py). For defect-free records at a range of temperatures against one 20 degC
baseline this prints, per ring and end condition:

- the residual energy (relative to the record's) left by the baseline at the *true* stretch
  (on the samples the stretched baseline covers),
  stretched whole ("plain", what BSS did before 2026-12-03) and with the burst kept
  ("thermal", what it does now);
- the stretch the search finds, as a fraction of the true one;
- the peak DI of ``assess`` (multipath, default threshold 0.02, no stretch bound), i.e. what a
  sound pipe's map shows at that temperature difference.

Physics: the project's 2-D SH FDTD (fullwave/, 600 mm pipe, 2 mm cells, clean records: no code
shared with the imaging) and the mock node's ray model (mocknode/, the paper pipe, default noise,
median of 3 records). True stretch: 1 / (1 + k dT) - 1 with the engines' k = -1e-4 per degC.

    .venv/bin/python bench/bench_thermal.py [--deltas -15 -10 ...]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import numpy as np  # noqa: E402

from fullwave.record import PipeModel, SimulationSpec, simulate  # noqa: E402
from fullwave.transducers import RingLayout  # noqa: E402
from imaging.compensation import best_stretch, stretch_traces  # noqa: E402
from imaging.measurement import Measurement  # noqa: E402
from imaging.pipeline import AssessSettings, assess  # noqa: E402
from imaging.resample import Resampler  # noqa: E402
from mocknode.physics import acquire  # noqa: E402
from mocknode.scenario import ExcitationSpec, NodeScenario, PipeSpec, RingSpec, TemperatureSpec  # noqa: E402

REFERENCE_C = 20.0
DELTAS_C = (-15.0, -10.0, -5.0, 3.0, 5.0, 10.0, 16.0, 20.0, 25.0, 30.0)
MOCK_SEEDS = (1, 2, 3)


def true_stretch(delta_c: float) -> float:
    return 1.0 / (1.0 - 1e-4 * delta_c) - 1.0


def relative_residual(current: Measurement, model: np.ndarray, stretch: float) -> float:
    """Of the samples the stretched baseline covers (a colder record's last few hold what arrived
    after the baseline's end: compensation takes the current's own samples there)."""
    target = current.traces.astype(np.float64)
    times = current.t0_s + np.arange(current.n_samples) / current.fs_hz
    covered = times / (1.0 + stretch) <= times[-1]
    return float(np.sum((target - model)[:, covered] ** 2) / np.sum(target * target))


def plain_stretch(m: Measurement, stretch: float) -> np.ndarray:
    """The whole record stretched, burst included (the model BSS used before)."""
    times = m.t0_s + np.arange(m.n_samples) / m.fs_hz
    return Resampler(m)(times / (1.0 + stretch))


def fdtd(n_transducers: int, ends: str) -> Callable[[float, int], Measurement]:
    def record(temperature_c: float, seed: int) -> Measurement:
        del seed  # clean records: one per temperature
        return simulate(SimulationSpec(pipe=PipeModel(length_mm=600.0, ends=ends),  # type: ignore[arg-type]
                                       rings=RingLayout(tx_axial_mm=150.0, n_transducers=n_transducers,
                                                        tx_rx_distance_mm=300.0),
                                       excitation_hz=75e3 if n_transducers == 8 else 85e3, cell_mm=2.0,
                                       n_samples=4000, temperature_c=temperature_c))
    return record


def mock(n_transducers: int, ends: str) -> Callable[[float, int], Measurement]:
    def record(temperature_c: float, seed: int) -> Measurement:
        scn = NodeScenario(node_id="bench", pipe=PipeSpec(ends=ends), rings=RingSpec(n_transducers=n_transducers),
                           excitation=ExcitationSpec(frequency_hz=75e3 if n_transducers == 8 else 85e3),
                           temperature=TemperatureSpec(mean_c=temperature_c, daily_amplitude_c=0.0,
                                                       jitter_c=0.0, reference_c=REFERENCE_C))
        return acquire(scn, 0.0, np.random.default_rng(seed)).to_measurement(scn)
    return record


SOURCES = {
    "FDTD 16-ring reflecting": (fdtd(16, "reflecting"), (0,)),
    "FDTD 16-ring absorbing": (fdtd(16, "absorbing"), (0,)),
    "FDTD 8-ring reflecting": (fdtd(8, "reflecting"), (0,)),
    "FDTD 8-ring absorbing": (fdtd(8, "absorbing"), (0,)),
    "mock 16-ring reflecting": (mock(16, "reflecting"), MOCK_SEEDS),
    "mock 16-ring absorbing": (mock(16, "absorbing"), MOCK_SEEDS),
    "mock 8-ring reflecting": (mock(8, "reflecting"), MOCK_SEEDS),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--deltas", type=float, nargs="+", default=DELTAS_C, help="temperature differences, degC")
    args = parser.parse_args()
    started = time.perf_counter()
    print(f"# defect-free records at 20 degC + dT against one 20 degC baseline; {time.strftime('%Y-%m-%d')}")
    for title, (record, seeds) in SOURCES.items():
        print(f"\n## {title} ({len(seeds)} record{'s' if len(seeds) > 1 else ''} per dT, medians)")
        print("| dT degC | true stretch | residual plain | residual thermal | found / true | peak DI |")
        print("|---|---|---|---|---|---|")
        for delta in args.deltas:
            s = true_stretch(delta)
            rows = []
            for seed in seeds:
                baseline, current = record(REFERENCE_C, seed + 100), record(REFERENCE_C + delta, seed)
                found, _ = best_stretch(baseline, current)
                result = assess(current, [baseline], AssessSettings())
                rows.append((relative_residual(current, plain_stretch(baseline, s), s),
                             relative_residual(current, stretch_traces(baseline, s), s), found / s,
                             result.peak_di if result.peak_di is not None else float("nan")))
            plain, thermal, ratio, peak = (statistics.median(column) for column in zip(*rows, strict=True))
            print(f"| {delta:+.0f} | {s:+.2e} | {plain:.1e} | {thermal:.1e} | {ratio:.3f} | {peak:.4f} |", flush=True)
    print(f"\nrun time {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
