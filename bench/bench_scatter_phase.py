"""A defect's scattered phase across the ring, on the project's own full-wave engine, and the axial error it makes.

Without end echoes the map places a defect by how its echo's arrival changes across the ring:
moving a scatterer by dz along the axis lengthens its path to every receiver by dz (1 - cos psi),
psi the scattering angle (between the incident wave, +z, and the way to the receiver). A defect
whose echo phase lags by b (1 - cos psi) is therefore imaged b / k further from the Tx ring
(docs/accuracy.md). This benchmark measures b for notches of five shapes and masses on the own SH engine
(16 transducers, 85 kHz, absorbing ends, the wave's circumference set to the record's pi x OD so
that the map's path lengths are exact) and prints it beside the error of ``pipesentry analyze``.

A heavy mass on a disc is nearly a clamped (rigid) disc: the areal mass of 1 kg on 20 mm is ~100x the
4 mm wall's. For each mass row the benchmark also prints the b of the exact 2-D solution for a clamped
disc of the mass's radius a (the scattered SH field's partial-wave series, ``clamped_disc_pattern``),
fitted on 1 - cos psi at the same receivers' psi and with the same weights: an analytic reference
the engine and the imaging share nothing with. Its phase follows b (1 - cos psi) to a few degrees,
so on direct paths the disc's size moves the map's peak by b / k (~ -a: towards the Tx ring, the
disc's lit side) and no axial position fitted to the direct paths can tell the two apart.

Per receiver, the residual (current - baseline) is fitted by least squares with the echo along
each of three legs round the pipe (the shorter way, the other way, once more round), each a
free complex amplitude times the receiver's own direct arrival (the baseline, moved to the leg's
arrival time: the pulse as the transducers shape it); the leg-0 amplitude's phase, relative to
the receiver in line with the defect, is fitted on 1 - cos psi over the receivers within
MAX_BEARING_DEG of it (farther round the two ways' arrivals coincide). Each simulation takes
~15-30 s on one core (cached in the full-wave cache: a second run takes seconds).

    .venv/bin/python bench/bench_scatter_phase.py [--cell-mm 0.5]
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from fullwave.cache import cached_simulation  # noqa: E402
from fullwave.defects import Defect, Mass, Notch  # noqa: E402
from fullwave.record import PipeModel, SimulationSpec  # noqa: E402
from fullwave.scattering import lag_on_one_minus_cos, leg0_phases  # noqa: E402
from fullwave.transducers import RingLayout  # noqa: E402
from imaging.analysis import analyze  # noqa: E402
from imaging.scatterers import clamped_disc_pattern  # noqa: E402

DEFECTS: list[tuple[str, Defect]] = [
    ("notch 20x10x2 mm", Notch(axial_mm=250.0, angle_deg=200.0)),
    ("notch 20x10x2 mm", Notch(axial_mm=150.0, angle_deg=30.0)),
    ("notch 4x4x1 mm", Notch(axial_mm=250.0, angle_deg=200.0, circumferential_mm=4.0, axial_length_mm=4.0,
                             depth_mm=1.0)),
    ("notch 20x10x3 mm", Notch(axial_mm=250.0, angle_deg=200.0, depth_mm=3.0)),
    ("notch 35x8x1.5 mm", Notch(axial_mm=250.0, angle_deg=200.0, circumferential_mm=35.0, axial_length_mm=8.0,
                                depth_mm=1.5)),
    ("notch 10x30x2 mm", Notch(axial_mm=250.0, angle_deg=200.0, circumferential_mm=10.0, axial_length_mm=30.0)),
    ("mass 0.05 kg, 6 mm", Mass(axial_mm=250.0, angle_deg=200.0, diameter_mm=6.0, mass_kg=0.05)),
    ("mass 1 kg, 20 mm", Mass(axial_mm=250.0, angle_deg=200.0, diameter_mm=20.0, mass_kg=1.0)),
    *((f"mass 1 kg, {d:.0f} mm", Mass(axial_mm=200.0, angle_deg=100.0, diameter_mm=d, mass_kg=1.0))
      for d in (6.0, 12.0, 20.0, 30.0)),
]
def base_spec(cell_mm: float) -> SimulationSpec:
    circumference = math.pi * PipeModel().outer_diameter_mm  # what the record reports: paths exact
    return SimulationSpec(pipe=PipeModel(ends="absorbing", circumference_mm=circumference),
                          rings=RingLayout(n_transducers=16), excitation_hz=85e3, cell_mm=cell_mm)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cell-mm", type=float, default=0.5, help="FDTD cell (the own cases': 0.5 mm)")
    args = parser.parse_args(argv)
    spec = base_spec(args.cell_mm)
    velocity = spec.pipe.steel.shear_velocity_m_s
    wavenumber = 2 * math.pi * spec.excitation_hz / (velocity * 1e3)  # rad / mm
    started = time.perf_counter()
    baseline = cached_simulation(spec)
    print(f"16 transducers, {spec.excitation_hz / 1e3:.0f} kHz, absorbing ends, wave circumference "
          f"{spec.pipe.wave_circumference_mm:.1f} mm (= the record's), cell {args.cell_mm} mm; "
          f"k = {wavenumber:.4f} rad/mm")
    print(f"{'defect':<20} {'at z / deg':>12} {'b rad':>7} {'b/k mm':>7} {'dz mm':>9} "
          f"{'lag in line -> far round (deg)':>31} {'DI':>7} detected  clamped disc b/k mm")
    for label, defect in DEFECTS:
        current = cached_simulation(dataclasses.replace(spec, defects=(defect,)))
        x, lag, amplitude = leg0_phases(baseline, current, defect.axial_mm, defect.angle_deg, velocity)
        weight = amplitude / amplitude.max()
        b = lag_on_one_minus_cos(x, lag, weight)
        disc = "-"
        if isinstance(defect, Mass):  # the exact clamped disc's lag at the same receivers' psi, weighted alike
            pattern = clamped_disc_pattern(wavenumber * defect.diameter_mm / 2, np.arccos(1.0 - x))
            exact = np.angle(pattern * np.conj(pattern[int(np.argmin(x))]))
            disc = f"{lag_on_one_minus_cos(x, exact, weight) / wavenumber:+.1f}"
        result = analyze(baseline, current)
        peak = result.peak  # the first reported defect's position, else the map's peak (below the threshold)
        dz = peak.axial_mm - defect.axial_mm if peak is not None else float("nan")
        order = np.argsort(x)
        trend = f"{math.degrees(lag[order[0]]):+.0f} -> {math.degrees(lag[order[-1]]):+.0f} (1-cos {x.max():.2f})"
        print(f"{label:<20} {defect.axial_mm:5.0f} / {defect.angle_deg:3.0f} {b:+7.2f} {b / wavenumber:+7.1f} "
              f"{dz:+9.1f} {trend:>31} {result.peak_di or 0.0:7.4f} {'yes' if result.detected else 'no':>8}  {disc:>18}")
    print(f"({time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
