"""One call for the gateway: assess a current record against a library of defect-free baselines.

    current + baselines --(health)--> healthy receivers --(OBS + BSS)--> matched baseline
        --(residual feature, all-paths map)--> defects (iterative) --> threshold --> Assessment

Every step is a pure function in its own module; this one only wires them, times the whole, and
judges a match beyond the residual or stretch bound (``strong_change``: a strong defect is
reported, a change of the ring or of the whole pipe is not). Abstains (``Assessment.valid_baseline``
False, no map) when no baseline matches.
"""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from imaging.arrivals import reference_amplitude
from imaging.compensation import (
    DEFAULT_MAX_RESIDUAL,
    DEFAULT_MAX_STRETCH,
    STRETCH_PER_DEGC,
    BaselineMatch,
    NoValidBaseline,
    as_recorded,
    at_thermometer_stretch,
    disagrees_with_thermometers,
    select_compatible_baseline,
    unexplained,
    with_common_gain,
)
from imaging.detection import default_threshold
from imaging.dimap import BaselineMismatch, DIMap, check_compatible, paper_di_map, windowed_energy
from imaging.features import FEATURES
from imaging.grid import Grid
from imaging.health import MAX_COMMON_GAIN_CHANGE, SensorFault, common_gain_change, healthy_mask, receiver_faults
from imaging.localize import Confidence, Estimate, locate_peak, peak_confidence
from imaging.measurement import Measurement
from imaging.modal import axisymmetric_fraction, default_modal_orders, remove_low_orders
from imaging.multidefect import explained_by_defects, find_defects
from imaging.multipath import path_model_for
from imaging.paths import signed_arc_mm
from imaging.region import Region, localization_region, receiver_lean, receiver_lean_mm
from imaging.scene import Scene

METHODS: tuple[str, ...] = ("multipath", "paper")
# A best baseline that leaves more than ``max_residual`` of the record unexplained is still the
# reference when the located defects the map finds explain at least this fraction of what it leaves:
# the change is a strong defect, not a wrong reference (docs/imaging.md, "A strong defect or a wrong
# reference"). Measured (bench/bench_reference_check.py, 2026-12-03): every strong defect of the dev
# and own full-wave sets 0.46-0.75; the wrong references tried were all told apart before this test
# (by the common gain and the axisymmetric share below), where they had scored 0.00-0.44.
MIN_EXPLAINED_BY_DEFECTS = 0.3
RING_MARGIN_MM = 10.0  # ... and whose strongest change lies this far from the Tx and Rx rings at least
MAX_AXISYMMETRIC = 0.6  # ... and when at most this share of what it leaves is common to every receiver
#                         (imaging/modal.py ``axisymmetric_fraction``: strong defects 0.05-0.47, other ends 0.80-1.00)


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
    common_gain: bool = True  # scale the matched baseline by the receivers' common gain where it explains the change
    # beyond max_residual (multipath), the records' temperatures overrule a stretch they disagree with
    thermometer: bool = True
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
    # Project the coherent map on its groups (ways round) jointly instead of adding their powers
    # (docs/imaging.md "The groups' overlap"; the default since 2026-12-05). Sparse-ring element
    # models add their powers either way.
    joint_groups: bool = True

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
class StrongChange:
    """A record imaged where a bound alone would have abstained: the baseline left ``residual`` (more
    than ``max_residual``), or the stretch search wanted ``refused_stretch`` (beyond the compensated
    range: the baseline as recorded was used), and the located defects explain ``explained`` of what
    it left (>= MIN_EXPLAINED_BY_DEFECTS, ``strong_change``): the defects are reported.
    ``searched_stretch``: the stretch the search had found, set aside for the one the records'
    temperatures predict (``AssessSettings.thermometer``; the match's ``stretch`` is theirs)."""

    residual: float
    max_residual: float
    explained: float
    refused_stretch: float | None = None
    searched_stretch: float | None = None

    def as_dict(self) -> dict:
        return {"residual": self.residual, "max_residual": self.max_residual, "explained_by_defects": self.explained,
                "refused_stretch": self.refused_stretch, "searched_stretch": self.searched_stretch}


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
    strong_change: StrongChange | None = None

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
        if self.strong_change is not None:
            out["strong_change"] = self.strong_change.as_dict()
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
                    reference_amplitude_v=reference_amplitude(entry), rx_mask=mask, project=project,
                    joint_groups=settings.joint_groups)


def _multipath(residual: np.ndarray, current: Measurement, scene: Scene, settings: AssessSettings,
               threshold: float, judge: bool) -> tuple[DIMap, Estimate, list[Defect], float]:
    """(first map, peak, defects, the fraction of the residual the located defects explain: computed
    only when ``judge``, else NaN) of ``residual``, the matched baseline less ``current``."""
    if scene.project is not None:
        residual = scene.project(residual)
    first, found, first_peak = find_defects(residual, scene, threshold=threshold, max_defects=settings.max_defects)
    explained = explained_by_defects(residual, scene, found) if judge else math.nan
    peak = found[0].estimate if found else first_peak
    lean = receiver_lean(scene.model)  # a sparse ring's angle leans to a receiver's line
    defects = []
    for f in found:
        conf = peak_confidence(f.di_map, f.peak, circumference_mm=scene.circumference_mm,
                               runner_up_di=f.runner_up_di)
        region = localization_region(conf, circumference_mm=current.circumference_mm,
                                     axial_span_mm=current.tx_rx_distance_mm)
        if f.map_peak is not None:  # placed by its echoes: the map's peak stays inside its region
            arc = signed_arc_mm(np.array(f.map_peak.angle_deg - f.estimate.angle_deg), current.circumference_mm)
            region = region.holding(f.map_peak.axial_mm - f.estimate.axial_mm, float(arc))
            for rival in f.axial_rivals_mm:  # ... and so do the places its echoes fit nearly as well
                region = region.holding(rival - f.estimate.axial_mm, 0.0)
        if lean:
            half = receiver_lean_mm(f.estimate.angle_deg, scene.rx_angles_deg[scene.rx_mask], current.circumference_mm,
                                    lean)
            region = region.round_at_least(half, current.circumference_mm)
        defects.append(Defect(f.estimate.axial_mm, f.estimate.angle_deg, f.estimate.di, conf, f.severity, region))
    return first, peak, defects, explained


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
        keep_best=True, common_gain=settings.common_gain,
    )
    limit = settings.max_compensated_stretch
    searched = None  # the search's stretch, when the thermometers overruled it
    if (settings.method == "multipath" and settings.thermometer and isinstance(match, BaselineMatch)
            and not match.residual <= THERMOMETERS_DECIDE_BEYOND):
        # A strong change: a near-rigid scatterer can buy a stretch no temperature made (docs/imaging.md,
        # "The records' temperatures"); where the records' own temperatures disagree with it beyond
        # what they can be wrong by, theirs is used. Not below: a sound pipe's record is what a wrong
        # thermometer would turn into a false alarm.
        # Also where the search's stretch lies beyond the compensated range and theirs within it: the
        # entry as recorded (below) would leave the whole temperature change in.
        by_thermometers = at_thermometer_stretch(baselines, compatible, current, mask)
        if by_thermometers is not None and abs(by_thermometers.stretch) <= settings.max_stretch and (
                disagrees_with_thermometers(match.stretch, by_thermometers.stretch)
                or (limit is not None and abs(match.stretch) > limit >= abs(by_thermometers.stretch))):
            searched, match = match.stretch, by_thermometers
    beyond: NoValidBaseline | None = None  # the stretch bound's abstention, while the entry as recorded is judged
    refused = None
    if isinstance(match, BaselineMatch) and limit is not None and abs(match.stretch) > limit:
        # A strong scatterer can buy a stretch no temperature made (docs/imaging.md): the entry as
        # recorded stands in if it passes the strong-change tests, else the record is abstained on.
        beyond, refused = _too_far_from_the_library(match, settings), match.stretch
        match = as_recorded(baselines, match.index, current, mask) if settings.method == "multipath" else beyond
    if (isinstance(match, BaselineMatch) and settings.common_gain and match.gain == 1.0
            and (match.stretch != 0.0 or beyond is not None or searched is not None)):
        # a drift hidden by the stretch until it was undone, or beside the entry as recorded
        match = with_common_gain(match, current, mask)
    if isinstance(match, BaselineMatch) and not match.residual <= settings.max_residual and (
            settings.method == "paper" or not math.isfinite(match.residual)):
        match = unexplained(match, settings.max_residual)  # only the multipath map can tell a defect from it
    if isinstance(match, NoValidBaseline):
        return _abstain(settings, threshold, match, faults, start)
    grid = settings.grid or default_grid(settings.method, current.tx_rx_distance_mm, current.rx_angles_deg)
    strong = None
    if settings.method == "paper":
        di_map, peak, defects = _paper(match, current, grid, mask, current.circumference_mm, threshold)
    else:
        over = beyond is not None or not match.residual <= settings.max_residual
        residual = match.baseline.traces.astype(np.float64) - current.traces.astype(np.float64)
        why = _changed_as_a_whole(match, residual, current, mask) if over else None
        if why is not None:
            return _abstain(settings, threshold, _refused(match, beyond, settings, why), faults, start)
        scene = scene_for(match, baselines[match.index], current, grid, mask, settings)
        di_map, peak, defects, explained = _multipath(residual, current, scene, settings, threshold, over)
        if over:
            judged = strong_change(match, defects, explained, settings.max_residual, current.tx_rx_distance_mm,
                                   refused, searched)
            if isinstance(judged, str):
                return _abstain(settings, threshold, _refused(match, beyond, settings, judged), faults, start)
            strong = judged
    elapsed = (time.perf_counter() - start) * 1e3
    return Assessment(settings.method, settings.feature, threshold, di_map, peak, defects, match, None, faults, elapsed,
                      strong_change=strong)


def strong_change(match: BaselineMatch, defects: list[Defect], explained: float, max_residual: float,
                  tx_rx_distance_mm: float, refused_stretch: float | None = None,
                  searched_stretch: float | None = None) -> StrongChange | str:
    """Judge a baseline that leaves more than ``max_residual`` of the record (or is used as recorded, the
    stretch search having wanted ``refused_stretch``; or warmed as the thermometers say, the search
    having found ``searched_stretch``): a strong defect (the StrongChange to report with its defects)
    or a wrong reference (why not, for the abstention).

    A strong defect is located (its strongest change is not at the Tx or Rx ring: a change there is
    the ring's own, or of what lies beyond it, such as another pipe's ends) and its echoes explain at
    least MIN_EXPLAINED_BY_DEFECTS of what the baseline leaves (``explained``: ``explained_by_defects``)."""
    if not defects:
        return "no defect is located in it: the reference is wrong or stale, or the pipe changed as a whole"
    z = defects[0].axial_mm
    if min(z, tx_rx_distance_mm - z) < RING_MARGIN_MM:
        ring = "Tx" if z < tx_rx_distance_mm / 2 else "Rx"
        return (f"its strongest change sits at the {ring} ring ({z:.0f} mm): a change of the transducers or of "
                "what lies beyond the ring, not a defect between the rings")
    if not explained >= MIN_EXPLAINED_BY_DEFECTS:
        return (f"the defects located explain {explained:.0%} of it (a strong defect explains at least "
                f"{MIN_EXPLAINED_BY_DEFECTS:.0%}): the reference is wrong or stale, or the pipe changed as a whole")
    return StrongChange(match.residual, max_residual, explained, refused_stretch, searched_stretch)


def _changed_as_a_whole(match: BaselineMatch, residual: np.ndarray, current: Measurement,
                        mask: np.ndarray) -> str | None:
    """Why what ``match`` leaves of ``current`` (``residual``) is a change of the ring or of the whole pipe,
    not of a point between the rings (None: it may be a defect's)."""
    gain = common_gain_change(match.baseline, current, mask)
    if abs(gain) > MAX_COMMON_GAIN_CHANGE:
        return (f"the direct arrival is {math.expm1(gain):+.0%} on most receivers alike: the transducers' gain or "
                "coupling changed, not the pipe (a defect moves only the receivers in its shadow); take a new "
                "baseline once the ring is checked and the pipe known sound")
    common = axisymmetric_fraction(residual, mask)
    if common > MAX_AXISYMMETRIC:
        return (f"{common:.0%} of it is the same on every receiver: the pipe's ends or what lies beyond the rings "
                "changed, or the reference is of another pipe (a point defect's echo differs from receiver to "
                "receiver)")
    return None


def _refused(match: BaselineMatch, beyond: NoValidBaseline | None, settings: AssessSettings,
             why: str) -> NoValidBaseline:
    """The abstention once the strong-change tests refused ``match``: the stretch bound's (``beyond``),
    or the residual bound's, with ``why``."""
    if beyond is None:
        return unexplained(match, settings.max_residual, why)
    return replace(beyond, reason=f"{beyond.reason} (unstretched, the baseline leaves {match.residual:.3g}: {why})")


def _abstain(settings: AssessSettings, threshold: float, why: NoValidBaseline, faults: list[SensorFault],
             start: float) -> Assessment:
    elapsed = (time.perf_counter() - start) * 1e3
    return Assessment(settings.method, settings.feature, threshold, None, None, [], None, why, faults, elapsed)


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


THERMOMETERS_DECIDE_BEYOND = DEFAULT_MAX_RESIDUAL  # residual share beyond which the records' temperatures
# may overrule the stretch search (AssessSettings.thermometer): whatever ``max_residual`` is set to
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
