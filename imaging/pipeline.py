"""One call for the gateway: assess a current record against a library of defect-free baselines.

    current + baselines --(health)--> healthy receivers --(OBS + BSS)--> matched baseline
        --(residual feature, all-paths map)--> defects (iterative) --> threshold --> Assessment

Every step is a pure function in its own module; this one only wires them and times the
whole. Abstains (``Assessment.valid_baseline`` False, no map) when no baseline matches.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from imaging.arrivals import reference_amplitude
from imaging.compensation import (
    DEFAULT_MAX_RESIDUAL,
    DEFAULT_MAX_STRETCH,
    STRETCH_PER_DEGC,
    BaselineMatch,
    NoValidBaseline,
    select_compatible_baseline,
)
from imaging.detection import default_threshold
from imaging.dimap import BaselineMismatch, DIMap, check_compatible, paper_di_map, windowed_energy
from imaging.features import FEATURES
from imaging.grid import Grid
from imaging.health import SensorFault, healthy_mask, receiver_faults
from imaging.localize import Confidence, Estimate, locate_peak, peak_confidence
from imaging.measurement import Measurement
from imaging.modal import default_modal_orders, remove_low_orders
from imaging.multidefect import find_defects
from imaging.multipath import path_model_for
from imaging.region import Region, localization_region
from imaging.scene import Scene

METHODS: tuple[str, ...] = ("multipath", "paper")


class SettingsError(ValueError):
    """AssessSettings holds an unknown method/feature or an out-of-range value."""


@dataclass(frozen=True)
class AssessSettings:
    """How to assess. ``threshold`` None: the documented default for the method and feature
    (imaging/detection.py). ``grid`` None: ``default_grid(method)``. ``wall_mm``: pipe wall
    thickness, for the mid-wall wrap length."""

    method: Literal["multipath", "paper"] = "multipath"
    feature: Literal["analytic", "envelope", "squared"] = "analytic"
    compensate: bool = True
    max_stretch: float = DEFAULT_MAX_STRETCH
    max_residual: float = DEFAULT_MAX_RESIDUAL
    # None: image whatever the stretch (a one-off analysis of two files); the gateway sets
    # DEFAULT_MAX_COMPENSATED_STRETCH, so that monitoring abstains instead of raising false alarms.
    max_compensated_stretch: float | None = None
    threshold: float | None = None
    max_defects: int = 3
    grid: Grid | None = None
    wall_mm: float | None = None
    model_ends: bool = True
    check_health: bool = True
    modal_orders: int | Literal["auto", "off"] = "off"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SettingsError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.feature not in FEATURES:
            raise SettingsError(f"unknown feature {self.feature!r}; choose one of {', '.join(FEATURES)}")
        if not 1 <= self.max_defects <= 16:
            raise SettingsError(f"max_defects must be 1..16, got {self.max_defects}")
        if self.threshold is not None and not math.isfinite(self.threshold):
            raise SettingsError("threshold must be finite")
        if not 0 <= self.max_stretch < 0.1:
            raise SettingsError("max_stretch must be in [0, 0.1)")
        if not self.max_residual > 0:
            raise SettingsError("max_residual must be positive")
        if self.max_compensated_stretch is not None and not 0 < self.max_compensated_stretch < 0.1:
            raise SettingsError("max_compensated_stretch must be None or in (0, 0.1)")
        if self.modal_orders not in ("auto", "off") and not (isinstance(self.modal_orders, int)
                                                             and 0 <= self.modal_orders <= 8):
            raise SettingsError(f"modal_orders must be 'auto', 'off' or 0..8, got {self.modal_orders!r}")

    def modal_orders_for(self, n_rx: int) -> int | None:
        """Circumferential orders 0..n removed from the residual before imaging (None: none)."""
        if self.modal_orders == "off":
            return None
        if self.modal_orders == "auto":
            return default_modal_orders(n_rx)
        return int(self.modal_orders)

    @property
    def effective_threshold(self) -> float:
        if self.threshold is not None:
            return self.threshold
        return default_threshold(self.method, self.feature)


@dataclass(frozen=True)
class Defect:
    """A detected defect: position, DI, confidence, severity (scattered / direct amplitude) and its
    90 % localization region (imaging/region.py; ``region.localized`` False: position not resolved)."""

    axial_mm: float
    angle_deg: float
    di: float
    confidence: Confidence
    severity: float
    region: Region

    def as_dict(self) -> dict:
        return {
            "axial_mm": self.axial_mm,
            "angle_deg": self.angle_deg,
            "di": self.di,
            "severity": self.severity,
            "confidence": self.confidence.as_dict(),
            "region": self.region.as_dict(),
        }


@dataclass(frozen=True)
class Assessment:
    """The outcome of one assessment. With ``valid_baseline`` False there is no map and no defect."""

    method: str
    feature: str
    threshold: float
    di_map: DIMap | None
    peak: Estimate | None
    defects: list[Defect]
    baseline: BaselineMatch | None
    no_valid_baseline: NoValidBaseline | None
    sensor_faults: list[SensorFault]
    elapsed_ms: float
    extra: dict = field(default_factory=dict)

    @property
    def valid_baseline(self) -> bool:
        return self.no_valid_baseline is None

    @property
    def peak_di(self) -> float | None:
        return None if self.peak is None else self.peak.di

    @property
    def detected(self) -> bool:
        return bool(self.defects)

    def as_json(self) -> dict:
        out = {
            "valid_baseline": self.valid_baseline,
            "method": self.method,
            "feature": self.feature if self.method == "multipath" else "squared",
            "detected": self.detected,
            "threshold": self.threshold,
            "peak_di": self.peak_di,
            "peak": None if self.peak is None else self.peak.as_dict(),
            "defects": [d.as_dict() for d in self.defects],
            "sensor_faults": [f.as_dict() for f in self.sensor_faults],
            "baseline": None if self.baseline is None else self.baseline.as_dict(),
            "elapsed_ms": self.elapsed_ms,
        }
        if self.di_map is not None:
            out["grid"] = self.di_map.grid.spec()
            out["window_samples"] = self.di_map.window_samples
        if self.no_valid_baseline is not None:
            out["no_valid_baseline"] = self.no_valid_baseline.as_dict()
        return {**out, **self.extra}


def paper_reference_energy(baseline: Measurement) -> float:
    """The paper DI the direct arrival alone would score: sum over receivers of its peak window energy."""
    from imaging.dimap import default_window_samples

    w = default_window_samples(baseline)
    energy = windowed_energy(baseline.traces.astype(np.float64), w, 0, baseline.n_samples)
    total = float(np.sum(energy.max(axis=1)))
    return total if total > 0 else 1.0


def _paper(match: BaselineMatch, current: Measurement, grid: Grid, mask: np.ndarray, circ: float,
           threshold: float) -> tuple[DIMap, Estimate, list[Defect]]:
    # Faulty receivers are left out by giving them a zero residual.
    masked = np.where(mask[:, None], current.traces, match.baseline.traces)
    from dataclasses import replace

    raw = paper_di_map(match.baseline, replace(current, traces=masked), grid)
    di_map = DIMap(raw.pixels / paper_reference_energy(match.baseline), grid, "paper", raw.window_samples)
    peak = locate_peak(di_map)
    defects = []
    if peak.di >= threshold:
        conf = peak_confidence(di_map, peak, circumference_mm=circ)
        severity = math.sqrt(max(peak.di, 0.0))
        region = localization_region(conf, circumference_mm=circ, axial_span_mm=current.tx_rx_distance_mm)
        defects.append(Defect(peak.axial_mm, peak.angle_deg, peak.di, conf, severity, region))
    return di_map, peak, defects


def scene_for(match: BaselineMatch, entry: Measurement, current: Measurement, grid: Grid, mask: np.ndarray,
              settings: AssessSettings) -> Scene:
    """What the record and its matched baseline share, resolved once (imaging/scene.py).

    End reflections and the reference amplitude are read off the library ``entry`` itself: a
    stretch of <= 0.5 % moves its arrivals, not their amplitudes, and the entry's values are
    memoised (imaging/arrivals.py), so a node's baselines are analysed once, not per measurement.
    """
    model = path_model_for(entry, wall_mm=settings.wall_mm, model_ends=settings.model_ends)
    orders = settings.modal_orders_for(current.n_rx)
    project = None
    if orders is not None:
        def project(x: np.ndarray) -> np.ndarray:
            return remove_low_orders(x, current.rx_angles_deg, orders, mask)

    return Scene.of(match.baseline, model, grid, feature=settings.feature,
                    reference_amplitude_v=reference_amplitude(entry), rx_mask=mask, project=project)


def _multipath(match: BaselineMatch, current: Measurement, scene: Scene, settings: AssessSettings,
               threshold: float) -> tuple[DIMap, Estimate, list[Defect]]:
    residual = match.baseline.traces.astype(np.float64) - current.traces.astype(np.float64)
    if scene.project is not None:
        residual = scene.project(residual)
    first, found, first_peak = find_defects(residual, scene, threshold=threshold, max_defects=settings.max_defects)
    peak = found[0].estimate if found else first_peak
    defects = []
    for f in found:
        conf = peak_confidence(f.di_map, f.estimate, circumference_mm=scene.circumference_mm,
                               runner_up_di=f.runner_up_di)
        region = localization_region(conf, circumference_mm=current.circumference_mm,
                                     axial_span_mm=current.tx_rx_distance_mm)
        defects.append(Defect(f.estimate.axial_mm, f.estimate.angle_deg, f.estimate.di, conf, f.severity, region))
    return first, peak, defects


def assess(current: Measurement, baselines: Sequence[Measurement], settings: AssessSettings | None = None) -> Assessment:
    """Assess ``current`` against a library of defect-free ``baselines`` (see the module docstring)."""
    settings = settings or AssessSettings()
    start = time.perf_counter()
    threshold = settings.effective_threshold
    if len(baselines) == 0:
        raise SettingsError("the baseline library is empty")
    # The one compatibility check of each (baseline, current) pair on this route.
    mismatches = [_mismatch(b, current) for b in baselines]
    compatible = [i for i, why in enumerate(mismatches) if why is None]
    faults: list[SensorFault] = []
    if settings.check_health and compatible:
        faults = receiver_faults(baselines[compatible[0]], current)
        # Most channels "faulty" at once is a common-mode change (another pipe, a wrong or
        # stale baseline), not broken transducers: leave it to baseline selection to judge.
        if len(faults) > current.n_rx // 2:
            faults = []
    mask = healthy_mask(current.n_rx, faults)
    match = select_compatible_baseline(
        baselines, compatible, current, compensate=settings.compensate, max_stretch=settings.max_stretch,
        max_residual=settings.max_residual, rx_mask=mask, mismatch=next((w for w in mismatches if w), None),
    )
    limit = settings.max_compensated_stretch
    if isinstance(match, BaselineMatch) and limit is not None and abs(match.stretch) > limit:
        match = _too_far_from_the_library(match, settings)
    if isinstance(match, NoValidBaseline):
        elapsed = (time.perf_counter() - start) * 1e3
        return Assessment(settings.method, settings.feature, threshold, None, None, [], None, match, faults, elapsed)
    grid = settings.grid or default_grid(settings.method, current.tx_rx_distance_mm, current.rx_angles_deg)
    if settings.method == "paper":
        di_map, peak, defects = _paper(match, current, grid, mask, current.circumference_mm, threshold)
    else:
        scene = scene_for(match, baselines[match.index], current, grid, mask, settings)
        di_map, peak, defects = _multipath(match, current, scene, settings, threshold)
    elapsed = (time.perf_counter() - start) * 1e3
    return Assessment(settings.method, settings.feature, threshold, di_map, peak, defects, match, None, faults, elapsed)


def _too_far_from_the_library(match: BaselineMatch, settings: AssessSettings) -> NoValidBaseline:
    """Abstain: even the best baseline needs more stretch than compensation keeps reliable, so a
    map would show the temperature, not the pipe (a false alarm waiting to happen)."""
    return NoValidBaseline(
        match.index,
        match.residual,
        settings.max_residual,
        f"the record is stretched {match.stretch:+.2%} against the closest baseline (about "
        f"{abs(match.stretch) / STRETCH_PER_DEGC:.0f} degC in steel), beyond the "
        f"{settings.max_compensated_stretch:.2%} compensation keeps reliable: set a baseline at this "
        "temperature once the pipe is known sound",
    )


MULTIPATH_STEP_MM = 4.0  # the multipath map (search and storage); peaks are refined at 1 mm x 1 deg
MULTIPATH_MAX_STEP_DEG = 4.0


def default_grid(method: str, tx_rx_distance_mm: float, rx_angles_deg: Sequence[float] | np.ndarray | None = None) -> Grid:
    """1 mm x 1 deg for the paper's method. For multipath 4 mm x (at most) 4 deg: its peaks are
    tens of mm wide, and every peak is refined on a local 1 mm x 1 deg grid (imaging/multidefect.py).
    The angle step divides the receiver spacing of an evenly spaced ring (3.75 deg for 8 or 16
    receivers), so every receiver shares one gather table, rolled (imaging/multipath.py)."""
    if method == "paper":
        return Grid.default(tx_rx_distance_mm)
    step_deg = MULTIPATH_MAX_STEP_DEG
    if rx_angles_deg is not None and len(rx_angles_deg) > 1:
        spacing = np.diff(np.sort(np.mod(np.asarray(rx_angles_deg, dtype=np.float64), 360.0)))
        even = 360.0 / len(rx_angles_deg)
        if np.allclose(spacing, even, atol=1e-6):
            step_deg = even / math.ceil(even / MULTIPATH_MAX_STEP_DEG - 1e-9)
    return Grid.default(tx_rx_distance_mm, axial_step_mm=MULTIPATH_STEP_MM, angle_step_deg=step_deg)


def _mismatch(baseline: Measurement, current: Measurement) -> str | None:
    """Why ``baseline`` cannot be compared with ``current`` (None: it can)."""
    try:
        check_compatible(baseline, current)
    except BaselineMismatch as exc:
        return str(exc)
    return None
