"""Several defects in one record: image, take the strongest peak, remove that scatterer's echoes, repeat.

The echoes of point scatterers at the positions found so far are modelled on every receiver
as one burst per modelled path (imaging/paths.py), each with a free amplitude and carrier
phase (a burst and its quadrature twin), fitted jointly to that receiver's residual by least
squares and subtracted from it. The next peak is then sought on the cleaned residual, away from the peaks
already found, until it falls below the detection threshold, or below MIN_RELATIVE_DI of the
first defect's DI (what the fit leaves of a strong defect is not a new one), or
``max_defects`` is reached. A last pass re-locates each defect (within REFINE_RADIUS_MM) with
the others' echoes removed.
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
MIN_RELATIVE_DI = 0.3  # ... and score at least this fraction of the first one's DI
REFINE_RADIUS_MM = 20.0  # the refinement pass may move an estimate this far at most


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
    positions: list[tuple[float, float]],
    *,
    rx_mask: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Joint least-squares fit, per receiver, of point scatterers' echoes at ``positions`` (axial_mm, angle_deg).

    Returns one fitted echo array [n_rx, n] per position (their sum is the full fit). Fitting
    the scatterers together keeps one from absorbing another's echoes where they overlap.
    """
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    mask = np.ones(n_rx, bool) if rx_mask is None else np.asarray(rx_mask, bool)
    in_phase, quadrature = burst_pair(reference.fs_hz, reference.excitation_hz, reference.cycles)
    c_mm_s = reference.velocity_m_s * MM_PER_M
    fitted = [np.zeros_like(residual) for _ in positions]
    for m in range(n_rx):
        if not mask[m]:
            continue
        columns, owner = [], []
        for p, (axial_mm, angle_deg) in enumerate(positions):
            rel = angle_deg - float(reference.rx_angles_deg[m])
            for _group, length, _w in scalar_paths(model, axial_mm, rel):
                k = math.floor((length / c_mm_s - reference.t0_s) * reference.fs_hz + 0.5)
                lo, hi = max(k, 0), min(k + in_phase.size, n)
                if hi <= lo:
                    continue
                for shape in (in_phase, quadrature):
                    col = np.zeros(n)
                    col[lo:hi] = shape[lo - k : hi - k]
                    columns.append(col)
                    owner.append(p)
        if not columns:
            continue
        design = np.stack(columns, axis=1)
        # Normal equations: 2 unknowns per path only; lstsq on the small Gram matrix copes with
        # coincident paths (identical columns) by taking the minimum-norm split between them.
        coef, *_ = np.linalg.lstsq(design.T @ design, design.T @ residual[m], rcond=1e-10)
        owner_arr = np.asarray(owner)
        for p in range(len(positions)):
            sel = owner_arr == p
            if sel.any():
                fitted[p][m] = design[:, sel] @ coef[sel]
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
    original = np.asarray(residual, dtype=np.float64)
    residual = original.copy()
    first: DIMap | None = None
    found: list[Found] = []
    fits: list[np.ndarray] = []

    def image(res: np.ndarray) -> tuple[np.ndarray, DIMap]:
        values = residual_feature(
            res, fs_hz=reference.fs_hz, excitation_hz=reference.excitation_hz, cycles=reference.cycles,
            reference_amplitude=reference_amplitude_v, feature=feature,
            window_samples=default_window_samples(reference),
        )
        pixels = multipath_pixels(
            values, reference.rx_angles_deg, grid, model, velocity_m_s=reference.velocity_m_s,
            t0_s=reference.t0_s, fs_hz=reference.fs_hz, power=power, rx_mask=rx_mask,
        )
        return values, DIMap(pixels, grid, "multipath", default_window_samples(reference))

    for _ in range(max_defects):
        values, di_map = image(residual)
        pixels = di_map.pixels
        first = first or di_map
        candidates = pixels.copy()
        for prior in found:
            candidates[exclusion_mask(grid, prior.estimate.axial_mm, prior.estimate.angle_deg,
                                      exclusion_mm, circumference_mm)] = -np.inf
        if not np.isfinite(candidates).any():
            break
        i, j = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        estimate = refine_peak(di_map, int(i), int(j))
        # What the echo fit leaves of a strong defect (the model is not the pipe) can cross an
        # absolute threshold; later defects must also be a fair fraction of the first.
        if estimate.di < threshold or (found and estimate.di < MIN_RELATIVE_DI * found[0].estimate.di):
            break
        severity = severity_at(values, reference, model, estimate, power=power, rx_mask=rx_mask)
        found.append(Found(estimate, di_map, severity))
        positions = [(f.estimate.axial_mm, f.estimate.angle_deg) for f in found]
        fits = fit_echoes(original, reference, model, positions, rx_mask=rx_mask)
        residual = original - sum(fits)
    assert first is not None
    if len(found) > 1:
        found = _refine(found, fits, original, image, reference, model, power, rx_mask, circumference_mm, exclusion_mm)
    return first, found


def _refine(found, fits, original, image, reference, model, power, rx_mask, circumference_mm, exclusion_mm):
    """One pass: re-locate each defect on the residual with every *other* defect's echoes removed.

    The search places each defect while the later ones are still in the residual, which biases
    the earlier peaks where their echoes overlap; re-imaging each with the others' (jointly
    fitted) echoes removed undoes most of that.
    """
    refined = []
    for i, item in enumerate(found):
        others = sum((f for j, f in enumerate(fits) if j != i), np.zeros_like(original))
        values, di_map = image(original - others)
        near = exclusion_mask(di_map.grid, item.estimate.axial_mm, item.estimate.angle_deg, REFINE_RADIUS_MM,
                              circumference_mm)
        candidates = np.where(near, di_map.pixels, -np.inf)
        a, b = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        estimate = refine_peak(di_map, int(a), int(b))
        severity = severity_at(values, reference, model, estimate, power=power, rx_mask=rx_mask)
        refined.append(Found(estimate, di_map, severity))
    return sorted(refined, key=lambda f: -f.estimate.di)
