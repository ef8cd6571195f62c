"""Several defects in one record: image, take the strongest peak, remove that scatterer's echoes, repeat.

The echoes of point scatterers at the positions found so far are modelled as one burst per
modelled path (imaging/paths.py) with the path's expected amplitude on each receiver and one
free amplitude and carrier phase per path (a burst and its quadrature twin) shared by all
receivers — the map's own scatterer model (imaging/echofit.py ``fit_smooth_echoes``) — fitted
jointly over all receivers and scatterers by least squares and subtracted from the residual.
The next peak is then sought on the cleaned residual, away from the peaks already found (and
from peaks ruled out), until it falls below the detection threshold, or below MIN_RELATIVE_DI
of the first defect's DI (what the fit leaves of a strong defect is not a new one), or has a
rival peak elsewhere nearly as high (UNRESOLVED_PEAK_RATIO: a map of fit leftovers is flat, a
second scatterer stands out of it), or ``max_defects`` is reached.

A real scatterer's field is directional, the map's model is an isotropic point: the fit leaves
a structured part of a strong defect's echoes, which the next pass can image as a spurious
defect. So a later peak is reported only if adding a scatterer there explains more of the
record than letting the found defects' echoes follow a directional pattern instead (each
path's amplitude a first-order circular harmonic of the receiver's bearing, PATTERN_ORDERS;
``_Search.beats_patterns``); otherwise it is ruled out and the search looks further. The pattern
is only the alternative hypothesis, never what is subtracted: removing the found defects' echoes
with it (tried, 2026-12-02) cut spurious defects further but also fitted away part of a weak
second notch's echoes wherever its paths overlapped the first's (DI ~0.05 -> ~0.03), so some
were lost (mock physics, bench/bench_defect_gate.py: 29 -> 27 of 32 notches). A faint later peak
(below FAINT_RELATIVE_DI of the first, down to MIN_RELATIVE_DI) must beat a richer alternative,
the second-order pattern (FAINT_PATTERN_ORDERS): the fainter a peak, the more of it the found
defects' leftovers can make (full-wave dev set: a notch beside a near-rigid mass at 0.19 of the
mass's DI is found; mock mode conversion leaves faint peaks on the notch's own line that the
first-order pattern let through, the second-order one does not). A second-order pattern for every
later peak was tried and lost a 1 mm-deep second notch at half the first's DI (mock). A later maximum on
either end of the imaged span (within EDGE_MM of the Tx or Rx ring), or in a ring's near field
(within NEAR_RING_WAVELENGTHS), is not a located scatterer — on the span's end the map would still
rise beyond it, in the near field its far-field paths do not hold; it is what changes at a ring (its
transducers, what leaks or converts there, the direct wave's shadow of a found defect) — so it is
not reported, but its echoes are fitted and removed with the defects' (they would bias them; a faint
one is only ruled out: fitting it moved the first defect on full-wave records, 26 -> 33 mm). So is a
later located peak that a change at a ring on its line (a scatterer on an end of the span at its
angle) explains as well (``_Search.ring_instead``): along a receiver's line the map is nearly flat,
and the joint map can place a ring's change tens of mm from it. The
strongest maximum of all is treated alike when it lies on the span's end: fitted, and the next peak
is sought as the first defect; it is reported only when nothing located crosses the threshold after
it and stands out of what the ring's fit leaves (no rival as high elsewhere: a sound pipe 3 degC
warmer than its baseline, uncompensated, leaves a flat map at 0.2 of the ring's change once that is
fitted, which a threshold of 0.01 would otherwise report as an unlocalized defect); a change at a
ring is still a change. A last pass re-locates
each defect (within REFINE_RADIUS_MM) with the others' echoes, those maxima's included, removed; a
later defect it moves into a ring's near field is dropped.

The search judges a later peak only against the defects found before it, so the first, the
strongest maximum, was never judged: on a sparse ring with end echoes what the fit leaves of a
strong scatterer can image higher than the scatterer itself. Once all are found and re-located,
every reported defect must therefore explain more of the record than the others' echoes with a
directional pattern (``_confirmed``, the same comparison as the search's, the faint ones against
the second-order pattern); the worst-explained one is dropped while it fails, and the rest are
judged again without it. The kept ones are not re-located after a drop (tried: the dropped
leftover's fit had been taking off what the isotropic model leaves of the strong defect, and
without it a kept mass moved 30 mm off and lost its localization).

A sparse ring's defects (the Tx ring modelled element by element), and any ring's on a record
without end echoes (``echo_placed``), are finally placed along their line where their echoes are
best explained (``_echo_fit_axial``), within the map's stated region, then turned round the pipe
within half a receiver pitch where the plain echo fit explains them best (``_echo_fit_angle``); a
sparse ring's are last placed along that line once more with each echo shape (forward lags, the
backward weight of a thinning) beside the plain point, one kept where decisively better (``_echo_fit_shape``).

The found defects' echoes are fitted along FIT_WRAPS legs round the pipe, more than the map's two:
the scattered wave keeps circling the pipe within the record (full-wave dev set, a notch's echoes
at its true position: the two legs leave 34 % of the record, six 7 %), and what the fit leaves of
the later turns otherwise images as spurious later defects. A dense ring's defect placed by its
echoes is placed along every leg that can arrive within the record (``fit_wraps``: 11 on a 600 us
record of the paper's pipe); the search keeps FIT_WRAPS, on which its gates were set. The map keeps
its two (more legs in the map itself were not tried).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from imaging.dimap import DIMap
from imaging.echofit import burst_pair, fit_echoes, fit_smooth_echoes  # noqa: F401  (burst_pair: re-exported)
from imaging.features import residual_feature
from imaging.grid import Grid
from imaging.localize import Estimate, exclusion_mask, parabolic_offset, peak_confidence, refine_peak
from imaging.multipath import local_multipath_pixels, multipath_pixels
from imaging.paths import PathModel
from imaging.region import localization_region
from imaging.scene import Scene
from imaging.timing import MM_PER_M

DEFAULT_EXCLUSION_MM = 50.0  # a second defect must lie this far (surface distance) from the first
MIN_RELATIVE_DI = 0.15  # ... and score at least this fraction of the first one's DI
FAINT_RELATIVE_DI = 0.3  # a later peak below this fraction of the first's is faint: at a ring it is not fitted,
#                         located it must beat the richer pattern (FAINT_PATTERN_ORDERS)
UNRESOLVED_PEAK_RATIO = 0.95  # ... and stand out: no rival peak (beyond 50 mm) at this fraction of its DI
REFINE_RADIUS_MM = 20.0  # the refinement pass may move an estimate this far at most
FINE_STEP_MM = 1.0  # peaks found on the (coarse) map grid are refined on a local grid this fine
FINE_STEP_DEG = 1.0
FINE_HALF_WIDTH = 2  # a defect's local grid spans +- this many coarse steps round the coarse peak
RUNNER_UP_HALF_WIDTH = 1  # ... a competing peak's (it only needs its height)
CONFIDENCE_EXCLUSION_MM = 50.0  # the competing peak of a defect's confidence lies this far away at least
COARSE_MARGIN = 0.5  # a later coarse peak below this fraction of the bar is not refined (lobes lose
#                     far less than half their height within half a coarse step)
RUNNER_UP_CANDIDATES = 3  # coarse local maxima refined to find a confidence's competing peak
FINE_MOVES = 3  # ... and may follow the peak this many times when it lies on the window's edge
EDGE_MM = 2.0  # a later peak this close to an end of the imaged span is a boundary maximum, not a located one
NEAR_RING_WAVELENGTHS = 0.5  # ... and one this close to a ring (in wavelengths) lies in its near field, where
#                             the map's far-field paths do not hold: what changes at the ring, not a scatterer
FIT_WRAPS = 6  # the found defects' echoes are fitted along this many legs round the pipe (the map: 2); a dense
#               ring's defect is placed by its echoes along every leg that arrives within the record (``fit_wraps``)
PATTERN_ORDERS = 1  # the alternative a later peak must beat: the found defects' echoes with each path's
#                     amplitude a circular harmonic of the receiver's bearing up to this order
FAINT_RELATIVE_DI_JOINT = 0.35  # ... on a map projecting its groups jointly (a defect whose groups overlap scores
#                                lower there: mock gate bench, 0.3 -> 0.35 took 15 spurious of 108 to 0, docs/imaging.md)
FAINT_PATTERN_ORDERS = 2  # ... up to this order for a faint one (below FAINT_RELATIVE_DI of the first)
ECHO_FIT_SPAN_MM = 40.0  # a sparse ring's defect is placed by its echo fit at most this far from the map's peak
ECHO_FIT_STEP_MM = 8.0  # ... searched at this step first (the fit's minimum is ~20-30 mm wide)
# ... each with its echoes lagging by b (1 - cos psi), psi the scattering angle, for b in these (rad), the
# best (position, b) kept where it leaves decisively less than no lag (``forward_lags``, ``_line_fit``): a
# notch's forward field lags (docs/imaging.md, "A forward lag fitted on sparse rings").
FORWARD_LAGS_RAD: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0)
EXTENTS_MM: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0)  # ... and, on any ring, lines this long round the pipe
BACKWARD_WEIGHT = True  # ... and each path's amplitude weighted by (1 - cos psi) / 2 tried beside them (``echo_shapes``)
ECHO_RIVAL_WAVELENGTHS = 2.0  # the echo fit's profile is searched this far either side of where it placed a defect
NOISE_MIN_SAMPLES = 64  # a receiver's noise is measured on at least this many samples before the first arrival
NOISE_FLOOR_SIGMAS = 3.0  # ... and the floor taken this many standard errors of that measurement below it
ECHO_RIVAL_MARGIN = 0.1  # ... for a local minimum leaving at most (1 + this) x the best: a rival position
ECHO_RIVAL_MIN_WAVELENGTHS = 0.5  # ... at least this far from the placed one (closer: the same minimum's flank)
ECHO_START_RATIO = 0.85  # the map's local maxima this close to its peak's height within that reach (and half a
#                         receiver pitch round the pipe) are further lines the defect is placed along
ECHO_STARTS = 2  # ... at most this many, highest first; one places the defect where its fit is decisively better
ECHO_FIT_ANGLE_STEP_DEG = 2.5  # ... then turned round the pipe within half a receiver pitch, at this step
ECHO_PLACED_MAX_DI = 0.5  # a dense ring's defect without end echoes is echo-placed only below this DI: a scatterer
#                          nearly as strong as the direct arrival is beyond the fit's single-scattering point (full-
#                          wave 16-ring records: notches 0.02-0.42, masses 0.65-0.93; docs/imaging.md)
DISC_RADII_MM: tuple[float, ...] = (5.0, 10.0, 15.0)  # a sparse ring's strong scatterer is also placed as a clamped
#                                                    disc of these radii (``_echo_fit_disc``)
PATTERN_MARGIN = 1.0  # ... by this factor: the patterned fit must leave this many times the energy
#                    (1.2 removes most spurious defects but loses weak second notches: docs/imaging.md)


class MultiDefectError(ValueError):
    """Bad arguments for the multi-defect search."""


@dataclass(frozen=True)
class EchoShape:
    """How a defect's echoes are modelled beyond the map's point: each path's carrier lagging by ``lag_rad``
    (1 - cos psi), and (``backward``) its amplitude weighted by (1 - cos psi) / 2 (a model with Tx elements
    only); a line ``extent_mm`` long round the pipe instead of a point (any model); a clamped disc of radius
    ``disc_mm`` (a model with Tx elements only) (imaging/echofit.py ``group_waves``)."""

    lag_rad: float = 0.0
    backward: bool = False
    extent_mm: float = 0.0
    disc_mm: float = 0.0


PLAIN = EchoShape()  # the map's isotropic point


@dataclass(frozen=True)
class Found:
    """One defect found by the search: the estimate, the map it was the peak of, and its severity."""

    estimate: Estimate
    di_map: DIMap
    severity: float
    runner_up_di: float | None = None  # the best peak outside CONFIDENCE_EXCLUSION_MM, refined alike
    map_peak: Estimate | None = None  # the map's peak, when the position comes from the echo fit instead
    shape: EchoShape = PLAIN  # its echoes' shape: a forward lag, the backward weight (sparse rings), an extent round
    #                           the pipe, where that fits decisively better than the plain point (``_echo_fit_shape``)
    axial_rivals_mm: tuple[float, ...] = ()  # where along its line its echoes fit nearly as well (``_echo_rivals``)

    @property
    def peak(self) -> Estimate:
        """The map's peak: the estimate itself unless the echo fit placed the defect (``_echo_fit_axial``)."""
        return self.map_peak or self.estimate


def severity_at(values: np.ndarray, scene: Scene, estimate: Estimate) -> float:
    """Least-squares scatterer strength at the estimate (the map's amplitude normalisation at one pixel)."""
    pixel = scene.with_grid(Grid(estimate.axial_mm, 1.0, 1, estimate.angle_deg, 1.0, 1))
    value = local_multipath_pixels(values, pixel, normalise="amplitude")[0, 0]
    return float(math.sqrt(max(value, 0.0)) if scene.power == 2 else value)


def _axis_window(centre: float, step: float, half: int, lo: float, hi: float) -> tuple[float, int]:
    """(start, count) of ``2 half + 1`` points ``step`` apart centred on ``centre``, cut to [lo, hi]."""
    first = -half if lo == -math.inf else max(-half, math.ceil((lo - centre) / step - 1e-9))
    last = half if hi == math.inf else min(half, math.floor((hi - centre) / step + 1e-9))
    return centre + first * step, max(1, last - first + 1)


def fine_peak(image_local: Callable[[Grid], np.ndarray], di_map: DIMap, i: int, j: int,
              allowed: Callable[[Grid], np.ndarray], half_width: int = FINE_HALF_WIDTH) -> Estimate:
    """The peak near pixel (i, j) of a coarse map, on a FINE_STEP_MM x FINE_STEP_DEG local grid.

    A window of +-``half_width`` coarse steps round the pixel is imaged at the fine step
    (``image_local``); while its best ``allowed`` pixel lies on an edge the window may still
    move (up to FINE_MOVES times), it follows the peak. The result is refined below the fine
    step like any peak (imaging/localize.py). When the coarse map is no coarser than the fine
    step the coarse pixel itself is refined.
    """
    grid = di_map.grid
    step_mm, step_deg = min(grid.axial_step_mm, FINE_STEP_MM), min(grid.angle_step_deg, FINE_STEP_DEG)
    if step_mm == grid.axial_step_mm and step_deg == grid.angle_step_deg:
        return refine_peak(di_map, i, j)
    half_z = round(half_width * grid.axial_step_mm / step_mm)
    half_a = round(half_width * grid.angle_step_deg / step_deg)
    z_lo, z_hi = grid.axial_start_mm, grid.axial_start_mm + grid.axial_step_mm * (grid.axial_count - 1)
    a_lo, a_hi = (-math.inf, math.inf) if grid.wraps_in_angle else (
        grid.angle_start_deg, grid.angle_start_deg + grid.angle_step_deg * (grid.angle_count - 1))
    centre_z = grid.axial_start_mm + grid.axial_step_mm * i
    centre_a = grid.angle_start_deg + grid.angle_step_deg * j
    for _ in range(FINE_MOVES + 1):
        z0, nz = _axis_window(centre_z, step_mm, half_z, z_lo, z_hi)
        a0, na = _axis_window(centre_a, step_deg, half_a, a_lo, a_hi)
        local = DIMap(image_local(Grid(z0, step_mm, nz, a0, step_deg, na)), Grid(z0, step_mm, nz, a0, step_deg, na),
                      di_map.method, di_map.window_samples)
        candidates = np.where(allowed(local.grid), local.pixels, -np.inf)
        a, b = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        moved_z = (a == 0 and z0 > z_lo + 1e-9) or (a == nz - 1 and z0 + step_mm * (nz - 1) < z_hi - 1e-9)
        moved_a = (b == 0 and a0 > a_lo + 1e-9) or (b == na - 1 and a0 + step_deg * (na - 1) < a_hi - 1e-9)
        if not (moved_z or moved_a):
            break
        centre_z, centre_a = z0 + step_mm * a, a0 + step_deg * b
    return refine_peak(local, int(a), int(b))


def _local_maxima(candidates: np.ndarray, wraps: bool, count: int) -> list[tuple[int, int]]:
    """The ``count`` highest finite pixels that are >= their 8 neighbours (angle wraps when ``wraps``)."""
    padded = np.pad(candidates, ((1, 1), (0, 0)), constant_values=-np.inf)
    padded = (np.pad(padded, ((0, 0), (1, 1)), mode="wrap") if wraps
              else np.pad(padded, ((0, 0), (1, 1)), constant_values=-np.inf))
    n_a, n_b = candidates.shape
    peak = np.isfinite(candidates)
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            if da or db:
                peak &= candidates >= padded[1 + da:1 + da + n_a, 1 + db:1 + db + n_b]
    flat = np.flatnonzero(peak)
    best = flat[np.argsort(-candidates.ravel()[flat], kind="stable")[:count]]
    return [(int(k) // n_b, int(k) % n_b) for k in best]


def _runner_up(image_local: Callable[[Grid], np.ndarray], di_map: DIMap, estimate: Estimate,
               circumference_mm: float) -> float:
    """The highest peak more than CONFIDENCE_EXCLUSION_MM from the estimate, refined like the estimate
    (the best of the RUNNER_UP_CANDIDATES highest local maxima of the coarse map there)."""
    def outside(g: Grid) -> np.ndarray:
        return ~exclusion_mask(g, estimate.axial_mm, estimate.angle_deg, CONFIDENCE_EXCLUSION_MM, circumference_mm)

    candidates = np.where(outside(di_map.grid), di_map.pixels, -np.inf)
    maxima = _local_maxima(candidates, di_map.grid.wraps_in_angle, RUNNER_UP_CANDIDATES)
    return max((fine_peak(image_local, di_map, i, j, outside, RUNNER_UP_HALF_WIDTH).di for i, j in maxima),
               default=0.0)


LocalImage = Callable[[Grid], np.ndarray]  # a feature's map on a small grid
Allowed = Callable[[Grid], np.ndarray]  # the pixels of a grid a peak may lie on


@dataclass(frozen=True)
class _Search:
    """One record's defect search: the residual as recorded and the scene it is imaged in."""

    original: np.ndarray
    scene: Scene

    def image(self, residual: np.ndarray) -> tuple[np.ndarray, DIMap]:
        """(feature, its map on the scene's grid)."""
        values = residual_feature(residual, self.scene)
        return values, DIMap(multipath_pixels(values, self.scene), self.scene.grid, "multipath",
                             self.scene.window_samples)

    def local_image(self, values: np.ndarray) -> LocalImage:
        return lambda local: local_multipath_pixels(values, self.scene.with_grid(local))

    def fits(self, found: list[Found], *, shared: bool = True, orders: int = 0,
             wraps: int | None = None) -> list[np.ndarray]:
        """Every found defect's echoes, fitted jointly, put through the scene's filter. ``shared``: each
        path's amplitude shared by all receivers, a circular harmonic of their bearing up to ``orders``
        (``fit_smooth_echoes``), else one per path and receiver (``fit_echoes``); each path followed
        along ``wraps`` legs round the pipe (imaging/paths.py ``wrap_turns``; default FIT_WRAPS); each
        defect's echoes with its ``shape`` (shared fits)."""
        positions = [(f.estimate.axial_mm, f.estimate.angle_deg) for f in found]
        scene = dataclasses.replace(self.scene, model=dataclasses.replace(self.scene.model, wraps=wraps or FIT_WRAPS))
        lags, backward = [f.shape.lag_rad for f in found], [f.shape.backward for f in found]
        extents, discs = [f.shape.extent_mm for f in found], [f.shape.disc_mm for f in found]
        fits = (fit_smooth_echoes(self.original, scene, positions, orders=orders, lags_rad=lags, backward=backward,
                                  extents_mm=extents, discs_mm=discs)
                if shared
                else fit_echoes(self.original, scene, positions))
        project = self.scene.project
        return fits if project is None else [project(f) for f in fits]

    def beats_patterns(self, found: list[Found], with_item: list[np.ndarray], orders: int = PATTERN_ORDERS) -> bool:
        """Does adding a scatterer at a candidate (the map's model; ``with_item``: the fits of
        ``found`` and the candidate) explain more of the record than letting the ``found``
        defects' echoes follow a directional pattern instead (each path's amplitude a circular
        harmonic of the receiver's bearing up to ``orders``)? The candidate has the fewer unknowns
        (2 per path, against 4 per path and found defect at order 1, 8 at order 2), so a tie goes
        to the pattern."""
        return self.pattern_ratio(found, with_item, orders) > PATTERN_MARGIN

    def pattern_ratio(self, found: list[Found], with_item: list[np.ndarray], orders: int) -> float:
        """What the ``found`` defects' echoes with a directional pattern up to ``orders`` leave of the
        record, over what ``with_item`` (their fits and a candidate's) leaves: above 1, the candidate
        explains more."""
        explained = float(np.sum((self.original - sum(with_item))**2))
        patterned = float(np.sum((self.original - sum(self.fits(found, orders=orders)))**2))
        if explained > 0:
            return patterned / explained
        return math.inf if patterned > 0 else 1.0

    def ring_instead(self, fitted: list[Found], item: Found, with_item: list[np.ndarray]) -> Found | None:
        """A change at a ring on the candidate's line (a scatterer on either end of the imaged span at
        its angle) that explains at least as much of the record as the candidate, fitted alike with
        the ``fitted`` echoes (``with_item``: theirs and the candidate's); None when the candidate
        explains more. Both have the same unknowns, so a tie goes to the ring (a ring's change is the
        commoner). Along a receiver's line every position gives that receiver the same delay; a map
        projecting its groups jointly can place a ring's change tens of mm along it (synthetic: 29.5 mm)."""
        explained = float(np.sum((self.original - sum(with_item))**2))
        best: Found | None = None
        for z in (float(self.scene.grid.axial_mm[0]), float(self.scene.grid.axial_mm[-1])):
            ring = Found(dataclasses.replace(item.estimate, axial_mm=z), item.di_map, 0.0)
            left = float(np.sum((self.original - sum(self.fits(fitted + [ring])))**2))
            if left <= explained:
                best, explained = ring, left
        return best

    def noise_floor(self) -> float:
        """What no fit of scatterers can explain of the record: every receiver not imaged, whole, and the noise
        of the imaged ones: the residual's mean square before the direct wave can reach the Rx ring (nothing the
        pipe does arrives earlier; a quarter burst spare) times the record's length, less NOISE_FLOOR_SIGMAS
        standard errors of that estimate (so that a floor measured on few samples is not taken for more than
        it is). No noise where the record holds fewer than NOISE_MIN_SAMPLES such samples."""
        scene, residual = self.scene, self.original
        burst = scene.cycles / scene.excitation_hz * scene.fs_hz
        first = (scene.model.tx_rx_distance_mm / (scene.velocity_m_s * MM_PER_M) - scene.t0_s) * scene.fs_hz
        quiet = min(residual.shape[-1], max(0, math.floor(first - burst / 4)))
        masked = float(np.sum(residual[~scene.rx_mask] ** 2))
        imaged = int(np.count_nonzero(scene.rx_mask))
        if quiet < NOISE_MIN_SAMPLES or not imaged:
            return masked
        noise = float(np.sum(np.mean(residual[scene.rx_mask, :quiet] ** 2, axis=-1))) * residual.shape[-1]
        return masked + noise * max(0.0, 1.0 - NOISE_FLOOR_SIGMAS * math.sqrt(2.0 / (quiet * imaged)))

    def found(self, values: np.ndarray, di_map: DIMap, estimate: Estimate) -> Found:
        runner_up = _runner_up(self.local_image(values), di_map, estimate, self.scene.circumference_mm)
        return Found(estimate, di_map, severity_at(values, self.scene, estimate), runner_up)


def find_defects(
    residual: np.ndarray,
    scene: Scene,
    *,
    threshold: float,
    max_defects: int,
    exclusion_mm: float = DEFAULT_EXCLUSION_MM,
) -> tuple[DIMap, list[Found], Estimate]:
    """(the first map, the defects whose peak DI reaches ``threshold``, strongest first, at most
    ``max_defects``; the first map's peak, refined on the fine grid).

    Maps are computed on ``scene.grid`` (coarse); every peak is then refined by ``fine_peak``. The
    first map's peak is ``Found`` position 0 when it crosses the threshold; the loop runs at
    most ``max_defects`` times and stops at the first peak below the threshold, so a record
    without a defect costs one map. ``scene.project``: the filter the residual has been through
    (e.g. imaging/modal.py); fitted echoes are put through it too before they are subtracted.
    """
    if max_defects < 1:
        raise MultiDefectError(f"max_defects must be at least 1, got {max_defects}")
    search = _Search(np.asarray(residual, dtype=np.float64), scene)
    circumference_mm, grid = scene.circumference_mm, scene.grid
    residual = search.original.copy()
    first: DIMap | None = None
    first_peak: Estimate | None = None
    found: list[Found] = []
    fits: list[np.ndarray] = []  # the found defects' echoes, fitted jointly

    def away_from(priors: list[Found]) -> Allowed:
        def allowed(g: Grid) -> np.ndarray:
            mask = np.ones(g.shape, bool)
            for prior in priors:
                mask &= ~exclusion_mask(g, prior.estimate.axial_mm, prior.estimate.angle_deg, exclusion_mm,
                                        circumference_mm)
            return mask
        return allowed

    ring_first: tuple[np.ndarray, DIMap, Estimate] | None = None  # the strongest maximum fitted at a ring
    rejected: list[Found] = []
    faint_rings: list[Found] = []  # faint maxima at a ring, ruled out by the search
    fitted: list[Found] = []  # found defects and maxima on a ring, in the order of their echoes in ``fits``
    reported: list[bool] = []  # per ``fitted``: a found defect (True) or a maximum on a ring, never reported
    for _ in range(2 * max_defects - 1):  # each pass reports a defect or rules a peak out
        if len(found) >= max_defects:
            break
        values, di_map = search.image(residual)
        first = first or di_map
        allowed = away_from(fitted + rejected)
        candidates = np.where(allowed(grid), di_map.pixels, -np.inf)
        if not np.isfinite(candidates).any():
            break
        i, j = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        if found and candidates[i, j] < COARSE_MARGIN * max(threshold, MIN_RELATIVE_DI * found[0].estimate.di):
            break  # far below what a further defect must reach: refining cannot lift it there
        estimate = fine_peak(search.local_image(values), di_map, int(i), int(j), allowed)
        first_peak = first_peak or estimate
        # What the echo fit leaves of a strong defect (the model is not the pipe) can cross an
        # absolute threshold; later defects must also be a fair fraction of the first.
        if estimate.di < threshold or (found and estimate.di < MIN_RELATIVE_DI * found[0].estimate.di):
            break
        at_a_ring = _on_the_span_edge(grid, estimate) if not found else _near_a_ring(scene, estimate)
        faint = bool(found) and _faint(scene, estimate.di, found[0].estimate.di)
        if at_a_ring and faint:
            rejected.append(Found(estimate, di_map, 0.0))  # too weak to bias the defects: not worth its unknowns
            faint_rings.append(rejected[-1])
            continue
        if at_a_ring:
            # A maximum on the Tx or Rx ring is not located (the map would still rise beyond the
            # imaged span): a change at a ring (its transducers, what leaks or converts there, the
            # direct wave's shadow), not a defect between them. Its echoes are fitted with the
            # defects' so that they stop biasing them, but it is not reported; the strongest
            # maximum is, when nothing located crosses the threshold after it (a change at a ring
            # is still a change). Later ones within a ring's near field are treated alike.
            ring_first = ring_first or (values, di_map, estimate)
            fitted.append(Found(estimate, di_map, severity_at(values, search.scene, estimate)))
            reported.append(False)
            fits = search.fits(fitted)
            residual = search.original - sum(fits)
            continue
        item = search.found(values, di_map, estimate)
        if fitted and (item.runner_up_di or 0.0) >= UNRESOLVED_PEAK_RATIO * estimate.di:
            # A later peak with a rival as high elsewhere: what the fits leave (a defect's or a change
            # at a ring's), not a new defect. After a change at a ring that is all the search stops on
            # before the first located defect; the tests below weigh a peak against defects found.
            break
        with_item = search.fits(fitted + [item])
        ring = search.ring_instead(fitted, item, with_item) if found else None
        if ring is not None:  # a change at a ring, imaged along its line: treated as a maximum at the ring
            if faint:
                rejected.append(item)
                continue
            fitted.append(dataclasses.replace(ring, severity=severity_at(values, search.scene, ring.estimate)))
            reported.append(False)
            fits = search.fits(fitted)
            residual = search.original - sum(fits)
            continue
        if found and not search.beats_patterns(fitted, with_item, FAINT_PATTERN_ORDERS if faint else PATTERN_ORDERS):
            rejected.append(item)  # what the found defects' directional fields leave: look further
            continue
        found.append(item)
        fitted.append(item)
        reported.append(True)
        fits = with_item
        residual = search.original - sum(fits)
    if first is None or first_peak is None:
        raise MultiDefectError("the map grid has no pixel to search")
    if not found and ring_first is not None:  # nothing located: the change at the ring is what there is
        return first, [search.found(*ring_first)], first_peak
    rings = [f for f, r in zip(fitted, reported, strict=True) if not r]
    if len(fitted) > 1 and found:
        # Each is re-located with the others' echoes removed, a dropped leftover's included: its
        # fit takes off what the isotropic model leaves of the defect that made it.
        found = _confirmed(search, _refine(search, fitted, fits, reported), rings)
    # Placed jointly with everything else the record holds, the faint maxima at a ring the search ruled
    # out included: a change at a ring on a defect's line otherwise pulls the defect along it.
    others = rings + faint_rings
    placed = [_echo_fitted(search, item, others + [f for f in found if f is not item])
              if echo_placed(scene.model, item.estimate.di) else item for item in found]
    if len(placed) > 1 and any(item.shape.disc_mm for item in placed):
        # A disc explains more of the record than the point the others were judged against: judged again
        placed = _confirmed(search, placed, rings)
    return first, placed, first_peak


def fit_wraps(scene: Scene, n_samples: int) -> int:
    """How many legs round the pipe (imaging/paths.py ``wrap_turns``) a defect placed by its echoes
    (``_unexplained_by``) is fitted along: on a sparse ring's element model FIT_WRAPS; on a dense ring's
    plane-wave model every leg that can arrive within the record (``n_samples`` long): the scattered wave
    circles the pipe as long as the record lasts. A leg k turns round the pipe is at least (k - 1/2)
    circumferences long.

    Fitted at the true position, what the fit leaves of a 16-ring notch's record without end echoes
    (the own engine, 2 mm cells, tests/imaging/test_fullwave_legs.py): 6 legs 0.27, 8 legs 0.14, 11 (all
    that arrive) 0.07. The fit drops legs that no receiver sees within the record (``fit_smooth_echoes``),
    so the bound costs only the legs that arrive. The element model keeps FIT_WRAPS: its paths are ~50x
    as many, and 8 legs lost the in-plane 8-ring mass (docs/imaging.md, "Echoes round the pipe"). The
    search keeps FIT_WRAPS too: with every leg there a mock 1 mm-deep second notch fell under the faint
    fraction and was lost (docs/imaging.md)."""
    if scene.model.elements:
        return FIT_WRAPS
    longest_mm = (scene.t0_s + n_samples / scene.fs_hz) * scene.velocity_m_s * MM_PER_M
    turns = math.floor(longest_mm / scene.model.circumference_mm + 0.5)  # the most turns a leg within it takes
    return max(FIT_WRAPS, 2 * turns + 1)


def echo_placed(model: PathModel, di: float) -> bool:
    """Is a defect of peak ``di`` imaged with ``model`` placed by its echo fit (``_echo_fitted``) rather
    than left on the map's peak?

    A sparse Tx ring's (modelled element by element, imaging/paths.py), and any ring's whose record
    holds only the direct paths (no end echoes: absorbing or unknown ends); on a dense ring only a
    defect below ECHO_PLACED_MAX_DI. Without end echoes the map's axial position rests on the
    path-length curvature across the ring, where the map's isotropic point leaves a notch, whose
    phase turns with the scattering angle, 9-32 mm towards the Rx ring (full-wave 16-ring records);
    its echoes, followed six times round the pipe with a first-order pattern, place it closer (22 of
    25 held-out notches; median 14.9 -> 6.9 mm). A scatterer nearly as strong as the direct arrival
    (the light and near-rigid masses, DI 0.65-0.93) is beyond that single-scattering point: placed,
    9 of 10 went further (map 3-19 mm off, placed 9-21), so on a dense ring it keeps the map's peak
    (re-measured 2026-12-08 with every leg and the lines: 18 held-out light masses map 1.5-12.9, placed 13.7-19.3).
    With end echoes the map's crossing paths fix the position (reflecting 16-ring notches 0.4-2.2 mm
    median). docs/imaging.md, "A dense ring's defect without end echoes placed by its echoes"."""
    return bool(model.elements) or (len(model.families()) == 1 and di < ECHO_PLACED_MAX_DI)


def explained_by_defects(residual: np.ndarray, scene: Scene, found: list[Found]) -> float:
    """The fraction of ``residual``'s energy (as imaged: after ``scene.project``) that the located
    defects among ``found`` explain: their echoes fitted jointly, each path's amplitude a circular
    harmonic of the receiver's bearing up to PATTERN_ORDERS (a strong scatterer's field is
    directional: the isotropic fit leaves much of a near-rigid point's). A maximum on the Tx or Rx
    ring counts nothing: what changes at a ring (a transducer's gain, an end echo of another pipe)
    is not a located defect. 0 when nothing is located or the residual is empty."""
    original = np.asarray(residual, dtype=np.float64)
    energy = float(np.sum(original * original))
    located = [f for f in found if not _on_the_span_edge(scene.grid, f.estimate)]
    if not located or not energy > 0:
        return 0.0
    fits = _Search(original, scene).fits(located, orders=PATTERN_ORDERS, wraps=scene.model.wraps)
    left = original - sum(fits)
    return max(0.0, 1.0 - float(np.sum(left * left)) / energy)


def _near_a_ring(scene: Scene, estimate: Estimate) -> bool:
    """Is a later peak on an end of the imaged span or within NEAR_RING_WAVELENGTHS of the Tx or Rx ring?

    There the scattered wave reaches the nearest receivers with (nearly) the direct arrival and
    the map's path model (far-field spreading, softened within half a wavelength) does not hold:
    a maximum there is what changes on a few receivers' direct arrival (a found defect's forward
    shadow, a transducer's gain), measured on full-wave records 8-14 mm before the Rx ring in line
    with a receiver, not a scatterer located between the rings."""
    near_mm = NEAR_RING_WAVELENGTHS * scene.wavelength_mm
    ring_mm = (0.0, float(scene.model.tx_rx_distance_mm))
    return _on_the_span_edge(scene.grid, estimate) or min(abs(estimate.axial_mm - z) for z in ring_mm) < near_mm


def _on_the_span_edge(grid: Grid, estimate: Estimate) -> bool:
    """Does the peak sit on either end of the imaged axial span (the Tx or the Rx ring), within EDGE_MM?"""
    first, last = _inside_the_span(grid)
    return estimate.axial_mm <= first or estimate.axial_mm >= last


def _inside_the_span(grid: Grid) -> tuple[float, float]:
    """(first, last) axial position (mm) more than EDGE_MM inside either end of the imaged span."""
    return float(grid.axial_mm[0]) + EDGE_MM, float(grid.axial_mm[-1]) - EDGE_MM


Unexplained = Callable[[Found, int], float]  # what a fit with a defect there, echoes up to that order, leaves


def _echo_fitted(search: _Search, item: Found, others: list[Found]) -> Found:
    """A defect placed by its echoes (``echo_placed``): along its line, then round the pipe, each
    trial position fitted jointly with the ``others``' echoes (``_unexplained_by``)."""
    unexplained = _unexplained_by(search, others)
    turned = _echo_fit_angle(_echo_fit_axial(search.scene, item, unexplained), unexplained, search.scene.n_rx)
    floor = search.noise_floor()
    return _echo_fit_disc(search.scene, _echo_fit_shape(search.scene, turned, unexplained, floor), unexplained, floor)


def _echo_fit_disc(scene: Scene, item: Found, unexplained_by: Unexplained, floor: float) -> Found:
    """A strong scatterer on a sparse ring (a model with Tx elements, peak DI at least ECHO_PLACED_MAX_DI) placed
    once more as a clamped disc (imaging/scatterers.py): turned round the pipe within half a pitch as the middle one of
    DISC_RADII_MM, then along its line as each; the best disc replaces the placed defect where
    what it leaves above ``floor`` is decisively less (ECHO_RIVAL_MARGIN) than what the placed one leaves.

    A heavy mass hardly lets the wall under it move; the sparse ring's incident field reaches it from every
    element image, from directions up to ~70 deg off the axis, and a disc of k a ~ 1-2 scatters those very
    unlike an isotropic point (half the amplitude at 90 deg, a phase lead). The point's fit is then worst at the
    mass itself and best on a receiver's line or at an alias elsewhere (own full-wave engine, 8 transducers,
    75 kHz, 1 kg on 20 mm at 200 mm, 10 deg round from a receiver: the point leaves 0.74 of the record at the
    truth, 0.24 on the receiver's line, the 10 mm disc 0.12 at the truth; docs/imaging.md, "A strong scatterer on
    a sparse ring fitted as a clamped disc"). The angle comes first because the disc's pattern depends on it most
    (turned as the middle radius, ~19 fits; each radius then along the line, ~11 fits each; another radius best:
    turned and along the line again as that one); the disc is tried only
    beside the placed defect (a shape is freedom, as ``_echo_fit_shape`` says)."""
    if not (scene.model.elements and DISC_RADII_MM and item.estimate.di >= ECHO_PLACED_MAX_DI):
        return item
    span = _echo_fit_span(scene, item) or ECHO_FIT_SPAN_MM  # a map that does not localize it: the fit's own reach
    first, last = _inside_the_span(scene.grid)
    middle = EchoShape(disc_mm=DISC_RADII_MM[len(DISC_RADII_MM) // 2])  # turned as the middle disc, then each along
    turned = _echo_fit_angle(dataclasses.replace(item, shape=middle, map_peak=item.peak), unexplained_by, scene.n_rx)
    lines = [_line_fit(turned, turned.estimate, span, first, last, unexplained_by, (EchoShape(disc_mm=r),))
             for r in DISC_RADII_MM]
    line = min((fit for fit in lines if fit is not None), key=lambda fit: fit.least, default=None)
    if line is None:
        return item
    if line.shape != middle:  # another radius fits best: turned as that one, and along its line again
        turned = _echo_fit_angle(dataclasses.replace(turned, shape=line.shape), unexplained_by, scene.n_rx)
        line = _line_fit(turned, turned.estimate, span, first, last, unexplained_by, (line.shape,)) or line
    placed = dataclasses.replace(turned, estimate=dataclasses.replace(turned.estimate, axial_mm=line.axial_mm),
                                 shape=line.shape)
    if not _decisively_less(unexplained_by(placed, PATTERN_ORDERS), unexplained_by(item, PATTERN_ORDERS), floor):
        return item
    return dataclasses.replace(placed, axial_rivals_mm=_echo_rivals(scene, line.axial_mm, line.along_its_shape))


def _echo_fit_shape(scene: Scene, item: Found, unexplained_by: Unexplained, floor: float = 0.0) -> Found:
    """A placed and turned defect (``_echo_fit_axial``, ``_echo_fit_angle``) placed once more along its line with
    the echo shapes of ``echo_shapes`` (forward lags, the backward weight, lines round the pipe) beside the
    position (``_line_fit``: a shape kept only where it leaves decisively less than the plain point), within the
    same stretch. Last, once
    its line and angle are fixed with the plain point: a shape is freedom that also absorbs a wrong line's or a
    wrong angle's mismatch (a synthetic scatterer with no lag, 1.25 deg round the pipe from the line it was
    fitted along, took lag 2 and moved 6 mm). ``floor``: what no fit explains (``_Search.noise_floor``), taken
    off both sides of that comparison: a noisy record's noise is no shape's to explain."""
    shapes = echo_shapes(scene.model)
    span = _echo_fit_span(scene, item)
    if item.map_peak is None or len(shapes) < 2 or span is None:
        return item
    first, last = _inside_the_span(scene.grid)
    line = _line_fit(item, item.estimate, span, first, last, unexplained_by, shapes, floor)
    if line is None or line.shape == PLAIN:
        return item
    return dataclasses.replace(item, estimate=dataclasses.replace(item.estimate, axial_mm=line.axial_mm),
                               shape=line.shape,
                               axial_rivals_mm=_echo_rivals(scene, line.axial_mm, line.along_its_shape))


def _unexplained_by(search: _Search, others: list[Found]) -> Unexplained:
    """What the echo fit (along ``fit_wraps`` legs) of a scatterer at a trial position, jointly with the ``others``' echoes
    (defects and maxima at a ring, where they are) and all with echoes up to the given order, leaves
    of the record: fitted together, the others cannot take up part of its echoes where their paths
    cross (synthetic two points without end echoes: 15.5 mm off with the others removed first, 2.4 mm
    fitted jointly)."""
    legs = fit_wraps(search.scene, search.original.shape[-1])

    def unexplained(at: Found, orders: int) -> float:
        leftover = search.original - sum(search.fits(others + [at], orders=orders, wraps=legs))
        return float(np.sum(leftover * leftover))

    return unexplained


def _echo_fit_span(scene: Scene, item: Found) -> float | None:
    """How far either way along its line the echo fit may place ``item``: the half-length of its map's stated 90 %
    region round the map's peak (imaging/region.py), at most ECHO_FIT_SPAN_MM; None where the map does not
    localize it."""
    region = localization_region(peak_confidence(item.di_map, item.peak, circumference_mm=scene.circumference_mm,
                                                 runner_up_di=item.runner_up_di),
                                 circumference_mm=scene.circumference_mm, axial_span_mm=scene.model.tx_rx_distance_mm)
    return min(ECHO_FIT_SPAN_MM, region.axial_half_mm) if region.localized else None


def _echo_fit_axial(scene: Scene, item: Found, unexplained_by: Unexplained) -> Found:
    """A defect (``echo_placed``) placed along its line (the map's angle) where its echoes are best
    explained: the axial position, within the map's own stated 90 % region round its peak
    (imaging/region.py; at most ECHO_FIT_SPAN_MM), that minimises what the echo fit (``fit_wraps`` legs) with a
    first-order directional pattern (PATTERN_ORDERS), jointly with the other defects' echoes, leaves
    of the record (``unexplained_by``). Coarse steps of at most ECHO_FIT_STEP_MM, half steps round the best, then
    the parabola through the best three, kept inside the region, with the plain point's echoes (the echo shapes
    come last, ``_echo_fit_shape``, once the line and angle are fixed). Where the map does not localize
    the defect at all its position is kept (there the fit was measured to wander: an 8-ring light
    mass with a searched stretch, 13 -> 40 mm). The DI, severity, runner-up and confidence stay
    the map's (``Found.peak``).

    With 8 elements the map's coherent sum leans on a few receivers and on the element model's
    incident field, and a strong scatterer's directional field pulls its peak along the axis (own
    full-wave free-end mass 26-30 mm off); the echoes themselves, round the pipe six times, place it
    within 3-6 mm. On a dense ring's record without end echoes it places the full-wave 16-ring notches
    closer than the map does (``echo_placed``); the echoes circle the pipe, so this needs the wrap
    the wave travels (``wall_mm``). The fit's further minima nearly as deep within two wavelengths are kept
    on the defect (``_echo_rivals``), for its region to hold them.

    The map's other maxima nearly as high within the fit's reach (``_echo_starts``) are further lines, each
    searched alike round its own maximum; one places the defect instead where its fit is decisively better
    elsewhere along the axis (``_moves_to``). Near an 8-ring's
    Tx ring the map's peak can lie beside the defect's own maximum: a held-out near-rigid mass 83 mm from
    the Tx ring peaked 40 mm and 7 deg away, its own maximum (0.92 of the peak) 9 mm from it; along that
    maximum's line the echoes leave 0.54 of what they leave along the peak's (reported 3.8 mm off, was 40.5)."""
    estimate = item.estimate
    span = _echo_fit_span(scene, item)
    if span is None:
        return item
    first, last = _inside_the_span(scene.grid)
    own = _line_fit(item, estimate, span, first, last, unexplained_by)
    if own is None:
        return item
    line = own
    for start in _echo_starts(scene, item):
        other = _line_fit(item, start, span, first, last, unexplained_by)
        if other is not None and _moves_to(other, line, own, scene.wavelength_mm):
            line = other
    rivals = _echo_rivals(scene, line.axial_mm, line.along_its_shape)
    return dataclasses.replace(item, estimate=dataclasses.replace(line.start, axial_mm=line.axial_mm, di=estimate.di),
                               map_peak=estimate, axial_rivals_mm=rivals)



@dataclass(frozen=True)
class _LineFit:
    """A defect placed along one line (``start``'s angle) by its echoes: where, with which echo shape, what the
    fit leaves there, and the fit along the line (``unexplained(z, shape)``, remembered)."""

    start: Estimate
    axial_mm: float
    shape: EchoShape
    least: float
    unexplained: Callable[[float, EchoShape], float]
    inside: bool  # placed inside the searched stretch, not on its end (where the fit goes on falling)

    def along_its_shape(self, axial_mm: float) -> float:
        return self.unexplained(axial_mm, self.shape)


def _moves_to(other: _LineFit, best: _LineFit, own: _LineFit, wavelength_mm: float) -> bool:
    """Whether a further line's fit (``other``) places the defect instead of the ``best`` so far: its least lies
    inside its stretch (on an end the fit goes on falling beyond it), it leaves less than the best by more than
    ECHO_RIVAL_MARGIN (within it, it is a rival: which one is the defect the record does not say), and it lies
    at least ECHO_RIVAL_MIN_WAVELENGTHS along the axis from where the peak's own line (``own``) placed it
    (nearer, it is the same place seen at another angle, which the angle search turns the defect to)."""
    return (other.inside and _decisively_less(other.least, best.least)
            and abs(other.axial_mm - own.axial_mm) >= ECHO_RIVAL_MIN_WAVELENGTHS * wavelength_mm)


def _decisively_less(left: float, than: float, floor: float = 0.0) -> bool:
    """Does an echo fit leaving ``left`` of the record explain it decisively better than one leaving ``than``: by
    more than ECHO_RIVAL_MARGIN, both counted above ``floor`` (what no fit explains, ``_Search.noise_floor``)?
    The rule for a rival line, an echo shape and a clamped disc alike."""
    return (1.0 + ECHO_RIVAL_MARGIN) * max(left - floor, 0.0) < than - floor


def forward_lags(model: PathModel) -> tuple[float, ...]:
    """The forward lags b (rad) a defect's echoes are tried with when it is placed along its line (``_line_fit``,
    which keeps a lag only where it leaves less than no lag by more than ECHO_RIVAL_MARGIN): FORWARD_LAGS_RAD on
    a sparse ring's element model, none but 0 on a plane-wave model, where a lag and the axial position trade
    exactly (docs/imaging.md, "A pattern by defect kind"); with 8 elements the scattering angle psi differs
    between element-receiver pairs that an axial move changes alike, so the two can be told apart.

    Tried last (``_echo_fit_shape``, once the line and angle are fixed with no lag) and kept only where decisively
    better: on the 8-ring cases of dev, own and four held-out draws the own absorbing notch 7.4 -> 1.0 mm, eight
    held-out notches closer (21.0 -> 8.1, 29.1 -> 18.2, 8.8 -> 2.4 mm ...), one further (2.6 -> 2.9), nothing
    else moved. Kept wherever it fitted best and tried with the line, a held-out near-rigid mass went 4.3 ->
    13.2 mm and the own pair of masses 5.3 / 7.2 -> 8.8 / 14.1 (docs/imaging.md)."""
    return FORWARD_LAGS_RAD if model.elements else (0.0,)


def echo_shapes(model: PathModel) -> tuple[EchoShape, ...]:
    """The echo shapes a placed defect is tried with last (``_echo_fit_shape``; one kept only where it leaves
    decisively less than the plain point, ``_line_fit``): each forward lag of ``forward_lags`` (the first: none,
    PLAIN) and, on a sparse ring's element model where BACKWARD_WEIGHT, the backward weight: a thinning of the
    wall scatters, to first order, in proportion to 1 - cos psi, a mass alike every way (docs/imaging.md, "A
    backward weight tried beside the lags on sparse rings"); on any ring, lines EXTENTS_MM long round the pipe
    (docs/imaging.md, "A defect's extent round the pipe"). With it, 8-ring cases of dev, own and two held-out draws: notches
    28.9 -> 20.4, 13.7 -> 5.5, 11.8 -> 8.4 mm, dev masses 0.3-0.9 mm closer, four defects 0.3-1.0 mm further;
    applied without the rule, a near-rigid mass went 6.6 -> 24.9 mm."""
    shapes = tuple(EchoShape(lag) for lag in forward_lags(model))
    shapes += (EchoShape(backward=True),) if model.elements and BACKWARD_WEIGHT else ()
    return shapes + tuple(EchoShape(extent_mm=e) for e in EXTENTS_MM)


def _line_fit(item: Found, start: Estimate, span: float, first: float, last: float,
              unexplained_by: Unexplained, shapes: tuple[EchoShape, ...] = (PLAIN,), floor: float = 0.0) -> _LineFit | None:
    """``_echo_fit_axial``'s search along ``start``'s line within ``span`` of it (None: too little of the line
    inside the imaged span, ``first`` to ``last``); among ``shapes`` holding PLAIN, a shape other than PLAIN kept
    only where what it leaves above ``floor`` is decisively less than what the plain point leaves above it (as a
    rival line must be); ``shapes`` without PLAIN: the best of them, unjudged."""
    lo = max(first, start.axial_mm - span)
    hi = min(last, start.axial_mm + span)
    if not hi - lo >= 2 * ECHO_FIT_STEP_MM:
        return None
    step = (hi - lo) / max(2, round((hi - lo) / ECHO_FIT_STEP_MM))
    left: dict[tuple[float, EchoShape], float] = {}

    def unexplained(z: float, shape: EchoShape) -> float:
        if (z, shape) not in left:
            at = Found(dataclasses.replace(start, axial_mm=z), item.di_map, item.severity, shape=shape)
            left[z, shape] = unexplained_by(at, PATTERN_ORDERS)
        return left[z, shape]

    coarse = np.linspace(lo, hi, 1 + round((hi - lo) / step))
    best, shape = min(((float(z), b) for b in shapes for z in coarse), key=lambda zb: unexplained(*zb))
    if shape != PLAIN and PLAIN in shapes:  # a shape only where the echoes support it: decisively better than none
        plain = min((float(z) for z in coarse), key=lambda z: unexplained(z, PLAIN))
        if not _decisively_less(unexplained(best, shape), unexplained(plain, PLAIN), floor):
            best, shape = plain, PLAIN
    half = (coarse[1] - coarse[0]) / 2
    z0, z1, z2 = best - half, best, best + half
    z_best = min((z0, z1, z2), key=lambda z: unexplained(z, shape))
    if z_best != z1:  # the half step moved the best: centre the parabola on it
        z0, z1, z2 = z_best - half, z_best, z_best + half
    offset = parabolic_offset(-unexplained(z0, shape), -unexplained(z1, shape), -unexplained(z2, shape))  # the vertex
    axial = float(np.clip(z1 + half * offset, lo, hi))
    return _LineFit(start, axial, shape, min(left.values()), unexplained, inside=lo < axial < hi)


def _echo_starts(scene: Scene, item: Found) -> list[Estimate]:
    """Further lines to place ``item`` along: local maxima of its whole coarse map that lie within the echo
    fit's reach of the map's peak (ECHO_RIVAL_WAVELENGTHS along the axis, half a receiver pitch round the
    pipe), at least ECHO_RIVAL_MIN_WAVELENGTHS from it along the axis, off its line by a map pixel at least,
    and at ECHO_START_RATIO of the highest pixel within reach or more; highest first, at most ECHO_STARTS."""
    di_map, estimate = item.di_map, item.estimate
    grid = di_map.grid
    wavelength = scene.wavelength_mm
    first, last = _inside_the_span(grid)
    dz = grid.axial_mm[:, None] - estimate.axial_mm
    arc_deg = np.abs(np.mod(grid.angle_deg[None, :] - estimate.angle_deg + 180.0, 360.0) - 180.0)
    reach = ((np.abs(dz) <= ECHO_RIVAL_WAVELENGTHS * wavelength) & (arc_deg <= 180.0 / scene.n_rx)
             & (grid.axial_mm[:, None] >= first) & (grid.axial_mm[:, None] <= last))
    if not reach.any():
        return []
    top = float(np.max(di_map.pixels[reach]))
    apart = np.abs(dz) >= ECHO_RIVAL_MIN_WAVELENGTHS * wavelength  # nearer: where the angle search turns it anyway
    across = arc_deg >= grid.angle_step_deg  # on the peak's own line the rival scan has stepped the fit already
    wanted = reach & apart & across & (di_map.pixels >= ECHO_START_RATIO * top)
    maxima = [(i, j) for i, j in _local_maxima(di_map.pixels, grid.wraps_in_angle, di_map.pixels.size) if wanted[i, j]]
    return [dataclasses.replace(estimate, axial_mm=float(grid.axial_mm[i]), angle_deg=float(grid.angle_deg[j]))
            for i, j in maxima[:ECHO_STARTS]]


def _echo_rivals(scene: Scene, axial_mm: float, unexplained: Callable[[float], float]) -> tuple[float, ...]:
    """Positions along a placed defect's line, within ECHO_RIVAL_WAVELENGTHS of ``axial_mm``, where the echo fit
    (``unexplained``) has another local minimum leaving at most (1 + ECHO_RIVAL_MARGIN) x the best, at least
    ECHO_RIVAL_MIN_WAVELENGTHS away: a cycle skip. Steps of ECHO_FIT_STEP_MM from ``axial_mm``; a local
    minimum within twice the margin is tried half a step either way before it is judged.

    A burst of a few cycles fits its own copy a wavelength of path later nearly as well, and an end echo's
    path changes by twice an axial move: on an 8-ring with free ends a notch 48 mm from the Tx ring
    (held-out full-wave draw) left 1.04 of the best at 40 mm and the best at 90, and was reported 40 mm
    off with a 27 mm region. Which minimum is the defect the record does not say; the region holds both
    (imaging/pipeline.py)."""
    wavelength = scene.wavelength_mm
    first, last = _inside_the_span(scene.grid)
    count = math.ceil(ECHO_RIVAL_WAVELENGTHS * wavelength / ECHO_FIT_STEP_MM)
    zs = [z for z in axial_mm + ECHO_FIT_STEP_MM * np.arange(-count - 1, count + 2) if first <= z <= last]
    values = [unexplained(float(z)) for z in zs]
    best = min(values)
    rivals = []
    for k in range(1, len(zs) - 1):
        if not (values[k] <= values[k - 1] and values[k] <= values[k + 1]
                and values[k] <= (1.0 + 2.0 * ECHO_RIVAL_MARGIN) * best):
            continue
        z, value = min(((float(zs[k]) + d, unexplained(float(zs[k]) + d) if d else values[k])
                        for d in (-ECHO_FIT_STEP_MM / 2, 0.0, ECHO_FIT_STEP_MM / 2)), key=lambda zv: zv[1])
        best = min(best, value)
        rivals.append((z, value))
    return tuple(z for z, value in rivals if value <= (1.0 + ECHO_RIVAL_MARGIN) * best
                 and abs(z - axial_mm) >= ECHO_RIVAL_MIN_WAVELENGTHS * wavelength)


def _echo_fit_angle(item: Found, unexplained_by: Unexplained, n_rx: int) -> Found:
    """A defect that ``_echo_fit_axial`` placed, turned round the pipe to where its echoes are best
    explained: the angle, within half a pitch of the ``n_rx`` receivers from the map's, that minimises
    what the *plain* echo fit (one amplitude per path, no directional pattern), jointly with the
    other defects' echoes, leaves of the record (``unexplained_by``); steps of ECHO_FIT_ANGLE_STEP_DEG, then the parabola through the
    best three. A defect the axial fit left alone (not localized) keeps the map's angle.

    The map's angle leans towards a receiver's: on an 8-ring at 75 kHz without end echoes a notch
    at 341 deg was reported at 360, 19 mm of arc off (held-out full-wave draw). The fit with a
    first-order pattern cannot turn it back, the pattern absorbs the angle (what it leaves was flat,
    0.24-0.26 of the record, over +-30 deg there); the plain fit's minimum lay at the truth (0.445
    against 0.55 at the map's angle)."""
    if item.map_peak is None:
        return item
    estimate = item.estimate
    left: dict[float, float] = {}

    def unexplained(angle: float) -> float:
        if angle not in left:
            at = dataclasses.replace(item, estimate=dataclasses.replace(estimate, angle_deg=angle % 360.0))  # its lag too
            left[angle] = unexplained_by(at, 0)
        return left[angle]

    steps = round(180.0 / n_rx / ECHO_FIT_ANGLE_STEP_DEG)
    angles = [estimate.angle_deg + k * ECHO_FIT_ANGLE_STEP_DEG for k in range(-steps, steps + 1)]
    k = int(np.argmin([unexplained(a) for a in angles]))
    angle = angles[k]
    if 0 < k < len(angles) - 1:
        angle += ECHO_FIT_ANGLE_STEP_DEG * parabolic_offset(-unexplained(angles[k - 1]), -unexplained(angle),
                                                          -unexplained(angles[k + 1]))
    return dataclasses.replace(item, estimate=dataclasses.replace(estimate, angle_deg=angle % 360.0))


def _faint(scene: Scene, di: float, strongest_di: float) -> bool:
    """Is a peak of ``di`` faint beside a defect of ``strongest_di`` (FAINT_RELATIVE_DI, or
    FAINT_RELATIVE_DI_JOINT on a map projecting its groups jointly)?"""
    return di < (FAINT_RELATIVE_DI_JOINT if scene.joint_groups else FAINT_RELATIVE_DI) * strongest_di


def _pattern_ratio(search: _Search, item: Found, others: list[Found]) -> float:
    """What the ``others``' echoes with a directional pattern leave of the record, over what a
    scatterer at ``item`` fitted with them leaves (``_Search.beats_patterns``'s comparison as a
    ratio: above PATTERN_MARGIN, ``item`` is a scatterer of its own). A faint item (below the
    faint fraction of the strongest other) faces the second-order pattern, as in the search."""
    strongest = max((f.estimate.di for f in others), default=0.0)
    orders = FAINT_PATTERN_ORDERS if _faint(search.scene, item.estimate.di, strongest) else PATTERN_ORDERS
    return search.pattern_ratio(others, search.fits(others + [item]), orders)


def _confirmed(search: _Search, found: list[Found], rings: list[Found]) -> list[Found]:
    """The reported defects that each explain more of the record than the others' echoes with a
    directional pattern (``_pattern_ratio``), judged once all are known. The search judges a later
    peak only against the defects found before it, so the first, the strongest maximum, is never
    judged: on a sparse ring with end echoes a scatterer's leftover can image higher than the
    scatterer (8 transducers, 75 kHz, a 1 kg mass on 20 mm at 92 mm 142 deg on the own engine: a
    maximum at 349 mm 316 deg, DI 0.99 against the mass's 0.82, that the mass with a first-order
    pattern explains better, ratio 0.77). The worst-explained defect is dropped while it fails,
    then the rest are judged again without it; ``rings``' echoes (maxima at a ring) stay fitted."""
    kept = list(found)
    while len(kept) > 1:
        ratios = [_pattern_ratio(search, item, rings + [f for f in kept if f is not item]) for item in kept]
        worst = int(np.argmin(ratios))
        if ratios[worst] > PATTERN_MARGIN:
            break
        del kept[worst]
    return kept


def _refine(search: _Search, found: list[Found], fits: list[np.ndarray], report: list[bool]) -> list[Found]:
    """One pass: re-locate each defect on the residual with every *other* defect's echoes removed.
    ``found`` and ``fits`` in the same order; only the items ``report`` marks are re-located and
    returned (strongest first), the others' echoes (maxima at a ring) are only removed.

    The search places each defect while the later ones are still in the residual, which biases
    the earlier peaks where their echoes overlap; re-imaging each with the others' (jointly
    fitted) echoes removed undoes most of that. The whole map is re-imaged (it is the
    defect's map, for its confidence); the peak is sought within REFINE_RADIUS_MM.
    """
    refined = []
    circumference_mm = search.scene.circumference_mm
    for i, item in enumerate(found):
        if not report[i]:
            continue
        others = sum((f for j, f in enumerate(fits) if j != i), np.zeros_like(search.original))
        values, di_map = search.image(search.original - others)

        def near(g: Grid, item: Found = item) -> np.ndarray:
            return exclusion_mask(g, item.estimate.axial_mm, item.estimate.angle_deg, REFINE_RADIUS_MM,
                                  circumference_mm)

        candidates = np.where(near(di_map.grid), di_map.pixels, -np.inf)
        if not np.isfinite(candidates).any():  # a coarse grid with no pixel that close: keep the estimate
            refined.append(item)
            continue
        a, b = np.unravel_index(int(np.argmax(candidates)), candidates.shape)
        estimate = fine_peak(search.local_image(values), di_map, int(a), int(b), near)
        if refined and _near_a_ring(search.scene, estimate):
            continue  # a later defect re-located onto a ring: what changes there, not a located one
        refined.append(search.found(values, di_map, estimate))
    return sorted(refined, key=lambda f: -f.estimate.di)
