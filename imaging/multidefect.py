"""Several defects in one record: image, take the strongest peak, remove that scatterer's echoes, repeat.

The echoes of a point scatterer at the found position are modelled on every receiver as one
burst per modelled path (imaging/paths.py), each with a free amplitude and carrier phase
(a burst and its quadrature twin), fitted to that receiver's residual by least squares and
subtracted. The next peak is then sought on the cleaned residual, away from the peaks
already found, until it falls below the detection threshold or ``max_defects`` is reached.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imaging.dimap import DIMap, default_window_samples
from imaging.features import residual_feature
from imaging.grid import Grid
from imaging.localize import Estimate, exclusion_mask, refine_peak
from imaging.measurement import Measurement
from imaging.multipath import feature_power, literal_multipath_pixels, multipath_pixels
from imaging.paths import PathModel, scalar_paths
from imaging.timing import MM_PER_M

DEFAULT_EXCLUSION_MM = 50.0  # a second defect must lie this far (surface distance) from the first


class MultiDefectError(ValueError):
    """Bad arguments for the multi-defect search."""


@dataclass(frozen=True)
class Found:
    """One defect found by the search: the estimate, the map it was the peak of, and its severity."""

    estimate: Estimate
    di_map: DIMap
    severity: float


def burst_pair(fs_hz: float, excitation_hz: float, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """The Hann burst and its quadrature twin (carrier shifted by 90 degrees): any carrier phase is a mix."""
    n = max(2, int(math.floor(cycles / excitation_hz * fs_hz)) + 1)
    t = np.arange(n) / fs_hz
    window = 0.5 * (1.0 - np.cos(2.0 * math.pi * excitation_hz * t / cycles))
    phase = 2.0 * math.pi * excitation_hz * t
    return window * np.sin(phase), window * np.cos(phase)


def fit_echoes(
    residual: np.ndarray,
    reference: Measurement,
    model: PathModel,
    axial_mm: float,
    angle_deg: float,
    *,
    rx_mask: np.ndarray | None = None,
) -> np.ndarray:
    """Least-squares fit, per receiver, of a point scatterer's echoes at (axial_mm, angle_deg); [n_rx, n]."""
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    mask = np.ones(n_rx, bool) if rx_mask is None else np.asarray(rx_mask, bool)
    in_phase, quadrature = burst_pair(reference.fs_hz, reference.excitation_hz, reference.cycles)
    c_mm_s = reference.velocity_m_s * MM_PER_M
    fitted = np.zeros_like(residual)
    for m in range(n_rx):
        if not mask[m]:
            continue
        columns = []
        for _family, length, _w in scalar_paths(model, axial_mm, angle_deg - float(reference.rx_angles_deg[m])):
            k = math.floor((length / c_mm_s - reference.t0_s) * reference.fs_hz + 0.5)
            lo, hi = max(k, 0), min(k + in_phase.size, n)
            if hi <= lo:
                continue
            for shape in (in_phase, quadrature):
                col = np.zeros(n)
                col[lo:hi] = shape[lo - k : hi - k]
                columns.append(col)
        if not columns:
            continue
        design = np.stack(columns, axis=1)
        # Normal equations: 2 x paths unknowns only; lstsq on the small Gram matrix copes with
        # coincident paths (identical columns) by taking the minimum-norm split between them.
        gram = design.T @ design
        coef, *_ = np.linalg.lstsq(gram, design.T @ residual[m], rcond=1e-10)
        fitted[m] = design @ coef
    return fitted


def severity_at(values: np.ndarray, reference: Measurement, model: PathModel, estimate: Estimate, *,
                power: int, rx_mask: np.ndarray | None) -> float:
    """Least-squares scatterer strength at the estimate (the map's amplitude normalisation at one pixel)."""
    pixel = Grid(estimate.axial_mm, 1.0, 1, estimate.angle_deg, 1.0, 1)
    value = literal_multipath_pixels(
        values, reference.rx_angles_deg, pixel, model, velocity_m_s=reference.velocity_m_s,
        t0_s=reference.t0_s, fs_hz=reference.fs_hz, power=power, rx_mask=rx_mask, normalise="amplitude",
    )[0, 0]
    return float(math.sqrt(max(value, 0.0)) if power == 2 else value)


def find_defects(
    residual: np.ndarray,
    reference: Measurement,
    grid: Grid,
    model: PathModel,
    *,
    feature: str,
    reference_amplitude_v: float,
    threshold: float,
    max_defects: int,
    rx_mask: np.ndarray | None = None,
    circumference_mm: float | None = None,
    exclusion_mm: float = DEFAULT_EXCLUSION_MM,
) -> tuple[DIMap, list[Found]]:
    """(the first map, the defects whose peak DI reaches ``threshold``, strongest first; at most ``max_defects``).

    The first map's peak is always in ``Found`` position 0 when it crosses the threshold; the
    loop runs at most ``max_defects`` times.
    """
    if max_defects < 1:
        raise MultiDefectError(f"max_defects must be at least 1, got {max_defects}")
    circumference_mm = circumference_mm or reference.circumference_mm
    power = feature_power(feature)
    residual = np.asarray(residual, dtype=np.float64).copy()
    first: DIMap | None = None
    found: list[Found] = []
    for _ in range(max_defects):
        values = residual_feature(
            residual, fs_hz=reference.fs_hz, excitation_hz=reference.excitation_hz, cycles=reference.cycles,
            reference_amplitude=reference_amplitude_v, feature=feature,
            window_samples=default_window_samples(reference),
        )
        pixels = multipath_pixels(
            values, reference.rx_angles_deg, grid, model, velocity_m_s=reference.velocity_m_s,
            t0_s=reference.t0_s, fs_hz=reference.fs_hz, power=power, rx_mask=rx_mask,
        )
        di_map = DIMap(pixels, grid, "multipath", default_window_samples(reference))
        first = first or di_map
        candidates = pixels.copy()
        for prior in found:
            candidates[exclusion_mask(grid, prior.estimate.axial_mm, prior.estimate.angle_deg,
                                      exclusion_mm, circumference_mm)] = -np.inf
        if not np.isfinite(candidates).any():
            break
        i, j = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        estimate = refine_peak(di_map, int(i), int(j))
        if estimate.di < threshold:
            break
        severity = severity_at(values, reference, model, estimate, power=power, rx_mask=rx_mask)
        found.append(Found(estimate, di_map, severity))
        residual -= fit_echoes(residual, reference, model, estimate.axial_mm, estimate.angle_deg, rx_mask=rx_mask)
    assert first is not None
    return first, found
