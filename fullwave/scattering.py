"""A defect's scattered phase across a ring of receivers, measured on a record, and an exact reference for it.

Without end echoes the map places a defect by how its echo's arrival changes across the ring: moving a
scatterer by dz along the axis lengthens its path to every receiver by dz (1 - cos psi), psi the scattering
angle (between the incident wave, +z, and the way to the receiver). A defect whose echo phase lags by
b (1 - cos psi) is therefore imaged b / k further from the Tx ring (docs/accuracy.md). ``leg0_phases``
measures that lag on a record pair, for the engine's scattering to be checked against the exact far field of a
clamped (rigid) disc, which a heavy mass on the wall is (1 kg on 20 mm is ~100x the 4 mm wall's areal mass;
imaging/scatterers.py ``clamped_disc_pattern``): tests/fullwave/test_fullwave_scattering.py and
bench/bench_scatter_phase.py. The engine itself uses none of it.
"""
from __future__ import annotations

import math

import numpy as np

from imaging.measurement import Measurement

MAX_BEARING_DEG = 115.0  # receivers this far round from the defect, either way, are fitted
LEGS = 3  # the echo's legs round the pipe fitted on each receiver


def _shifted(pulse: np.ndarray, delay_samples: float) -> np.ndarray:
    """``pulse`` delayed by a fraction of samples (Fourier shift; the record is long and quiet at its end)."""
    n = pulse.size
    spectrum = np.fft.rfft(pulse, 2 * n)
    f = np.fft.rfftfreq(2 * n)
    return np.fft.irfft(spectrum * np.exp(-2j * np.pi * f * delay_samples), 2 * n)[:n]


def _quadrature(pulse: np.ndarray) -> np.ndarray:
    """The pulse with its carrier a quarter period later (its Hilbert transform)."""
    n = pulse.size
    spectrum = np.fft.rfft(pulse, 2 * n)
    return np.fft.irfft(spectrum * -1j, 2 * n)[:n]


def leg0_phases(baseline: Measurement, current: Measurement, axial_mm: float, angle_deg: float,
                velocity_m_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(1 - cos psi, leg-0 phase lag in rad relative to the receiver nearest in line, |amplitude|),
    for the receivers within MAX_BEARING_DEG of the defect."""
    c_mm_s = velocity_m_s * 1e3
    circ = baseline.circumference_mm
    dz = baseline.tx_rx_distance_mm - axial_mm
    direct_s = baseline.tx_rx_distance_mm / c_mm_s
    residual = current.traces.astype(np.float64) - baseline.traces.astype(np.float64)
    rows = []
    for m, rx_deg in enumerate(baseline.rx_angles_deg):
        bearing = (angle_deg - float(rx_deg) + 180.0) % 360.0 - 180.0
        if abs(bearing) > MAX_BEARING_DEG:
            continue
        arc = bearing * circ / 360.0
        way = 1.0 if arc >= 0 else -1.0
        legs = [arc, arc - way * circ, arc + way * circ][:LEGS]
        pulse = baseline.traces[m].astype(np.float64)
        columns = []
        for leg in legs:
            delay = ((axial_mm + math.hypot(dz, leg)) / c_mm_s - direct_s) * baseline.fs_hz
            moved = _shifted(pulse, delay)
            columns += [moved, _quadrature(moved)]
        coef, *_ = np.linalg.lstsq(np.stack(columns, axis=1), residual[m], rcond=None)
        amplitude = complex(coef[0], coef[1])  # in-phase + quadrature: the carrier lags by arg
        rows.append((1.0 - dz / math.hypot(dz, arc), abs(bearing), amplitude))
    one_minus_cos = np.array([r[0] for r in rows])
    amplitudes = np.array([r[2] for r in rows])
    reference = amplitudes[int(np.argmin([r[1] for r in rows]))]
    lag = np.angle(amplitudes * np.conj(reference))  # wrapped to +-pi round the in-line receiver's
    return one_minus_cos, lag, np.abs(amplitudes)


def lag_on_one_minus_cos(x: np.ndarray, lag: np.ndarray, weight: np.ndarray) -> float:
    """b of lag = b (1 - cos psi) through 0, least squares weighted by ``weight``."""
    return float(np.sum(weight * x * lag) / np.sum(weight * x * x))


__all__ = ["lag_on_one_minus_cos", "leg0_phases"]
