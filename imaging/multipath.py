"""The all-paths DI map: delay-and-sum of a residual feature along every modelled scattering path.

Real features (envelope, squared), an incoherent sum:
    DI(pixel) = sum_m sum_p w_mp^q F_m[k_mp] / sqrt(sum_m sum_p w_mp^(2q))
Complex features (analytic), coherent within each group g of paths (a path family and one way
round the pipe, imaging/paths.py ``coherence_groups``), the groups projected on jointly
(``Scene.joint_groups``, the default):
    DI(pixel) = sqrt( b^H M^-1 b / G ),  b_g = sum_{m, p in g} w_mp A_m[k_mp],
    M_gh = sum_m sum_{p in g, q in h} w_mp w_mq C(k_mq - k_mp)
(C the normalised feature's complex noise autocorrelation, imaging/arrivals.py): the two ways
round reach a receiver near the scatterer's far side within a burst of each other, so their
templates overlap; or, with ``joint_groups=False`` and always for a sparse ring's element model,
added in power as if they did not (which moves a point 10-17 mm towards the Rx ring where the
axial lobe is broad, docs/imaging.md "The groups' overlap"):
    DI(pixel) = sqrt( sum_g |b_g|^2 / sum_{m, p in g} w_mp^2 / G )

over healthy receivers m and paths p, where k_mp = round((L_mp / c - t0) fs) is the sample at
which path p's burst starts, F/A the normalised feature (imaging/features.py), w the path's
expected amplitude and q = 1 for an amplitude feature, 2 for an energy feature. Both are the
matched-filter (generalised likelihood ratio) statistic of a point scatterer at the pixel; the
coherent form has one unknown complex amplitude per group, because a defect's scattered phase
is nearly the same for every receiver reached by the same route but differs between forward,
back and sideways scattering, and a route the data lack (e.g. an end that does not reflect)
then costs nothing at the true position. G, the model's number of groups, makes noise alone
score the same whatever the model (each group adds one complex unknown: DI^2 of noise is a
mean of G terms, not a sum), so one threshold serves pipes with and without reflecting ends.
Noise alone gives a map of about the same spread everywhere, so the arg-max is the position estimate and its value can be compared with a
fixed threshold. With ``normalise="amplitude"`` the map is the least-squares scatterer
strength instead: DI sqrt(G) / sqrt(sum of all w^2) (coherent) or the weighted sum / sum w^(2q).
Samples outside the record contribute nothing.

A sparse Tx ring's element-by-element incident wave (imaging/paths.py) puts several paths of one
group on one receiver, close together in time; their noise is then correlated, and the group's
sum of squared weights becomes sum_ab w_a w_b r(|k_a - k_b|) per receiver (imaging/gather.py
``coherent_energy``), so that noise alone still scores the same as with a plane wave.

Fast path: for each receiver the (sample index, weight) of every path and pixel is computed
once per geometry and cached; receivers a whole number of grid steps apart share one table,
rolled in angle per receiver.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from cachetools import LRUCache, cached

from imaging.arrivals import (
    analytic_noise_correlation,
    analytic_noise_covariance,
    end_reflection_coefficients,
    reference_amplitude,
)
from imaging.dimap import DIMap, check_compatible
from imaging.features import residual_feature
from imaging.gather import accumulate, coherent_energy, cross_gram, joint_power, local_sums_compiled, pack_lower
from imaging.grid import Grid
from imaging.measurement import Measurement
from imaging.paths import PathModel, coherence_groups, scalar_paths, scatter_paths, sparse_ring, stacked_paths
from imaging.ring_fit import fit_sparse_ring
from imaging.scene import Scene
from imaging.timing import MM_PER_M

NORMALISATIONS = ("snr", "amplitude")
LOCAL_GRAM_CACHE = 128  # small grids' Gram whitenings kept (a 17 x 17 grid's: ~0.1 MB with 8 groups)
GRAM_RIDGE = 1e-6  # the groups' cross-Gram is factored (whitened) with this fraction of its largest diagonal term added
#                   to the diagonal (a group without paths there, or two coinciding ones, stay finite)
GRAM_BLOCK_PIXELS = 1 << 13  # a grid's Grams are summed and factored this many pixels (whole rings) at a time
REFLECTION_QUANTUM = 0.05  # end reflection coefficients are used to the nearest 0.05
WRAP_QUANTUM_MM = 0.5  # ... and a sparse ring's fitted wrap length to the nearest 0.5 mm (0.15 % of the paper's)
# A sparse ring is modelled element by element only where its baseline shows it: the element model
# must leave at most this fraction of what a plane wave leaves unexplained (imaging/ring_fit.py).
# Measured (2026-12-03): SH full-wave 8-ring baselines 0.33-0.64; the mock node's 2.5-13.9 (its
# physics launches a plane wave); the own in-plane model's 2.2 (tilted patches: order 8 hardly there).
ELEMENTS_EVIDENCE = 0.8


class MultipathError(ValueError):
    """Bad arguments to the all-paths imaging (shapes, masks, normalisation)."""


def _safe_divide(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _reciprocal(den: np.ndarray) -> np.ndarray:
    """1 / den where den > 0, else 0."""
    return np.where(den > 0, 1.0 / np.where(den > 0, den, 1.0), 0.0)


def _combine(groups: np.ndarray, weight_sq: np.ndarray, normalise: str,
             inverse_weight_sq: np.ndarray | None = None, whitening: np.ndarray | None = None) -> np.ndarray:
    """Groups [n_groups, ...] and their summed squared weights -> the map (module docstring).

    ``inverse_weight_sq``: ``_reciprocal(weight_sq)`` when it is at hand (cached with the tables).
    ``whitening``: the whitening of the groups' (ridged) cross-Gram M, packed (``gram_whitening``); with
    it a coherent map projects on the groups jointly (b^H M^-1 b) instead of adding their powers."""
    total_sq = np.sum(weight_sq, axis=0)
    if np.iscomplexobj(groups):
        if whitening is not None:
            joint = joint_power(groups, whitening)
            snr = np.sqrt(np.maximum(joint, 0.0) / groups.shape[0])
            return snr if normalise == "snr" else _safe_divide(snr * np.sqrt(groups.shape[0]), np.sqrt(total_sq))
        if inverse_weight_sq is None:
            inverse_weight_sq = _reciprocal(weight_sq)
        # squared in double: a single-precision sum of near-null weights (a polarised path almost along
        # the ring, w^2 ~ 1e-27) squares below single precision's range, and the map there went to 0
        power = (np.square(groups.real, dtype=np.float64) + np.square(groups.imag, dtype=np.float64)) * inverse_weight_sq
        snr = np.sqrt(np.sum(power, axis=0) / groups.shape[0])
        return snr if normalise == "snr" else _safe_divide(snr * np.sqrt(groups.shape[0]), np.sqrt(total_sq))
    weighted = np.sum(groups, axis=0)
    return _safe_divide(weighted, np.sqrt(total_sq) if normalise == "snr" else total_sq)


@dataclass(frozen=True)
class GatherTable:
    """One receiver angle's gather table: per in-record path its coherence ``groups`` [P] (int64), sample
    ``idx`` [P, n_pixels] (int32; ``n_samples`` = outside the record, a zero appended to the feature)
    and ``w`` [P, n_pixels] (weight**power, float32); and ``weight_sq`` [n_groups, n_pixels], per
    group the sum of weight**(2 power) over its in-record paths."""

    groups: np.ndarray
    idx: np.ndarray
    w: np.ndarray
    weight_sq: np.ndarray

    @property
    def nbytes(self) -> int:
        """What the table holds in memory (the table cache's measure)."""
        return int(self.groups.nbytes + self.idx.nbytes + self.w.nbytes + self.weight_sq.nbytes)


def build_table(
    grid: Grid,
    rx_angle_deg: float,
    model: PathModel,
    velocity_m_s: float,
    t0_s: float,
    fs_hz: float,
    n_samples: int,
    power: int,
    excitation_hz: float = 0.0,
    cycles: int = 0,
) -> GatherTable:
    """The gather table of a receiver at ``rx_angle_deg`` (uncached). Paths never inside the record are dropped.

    ``excitation_hz`` and ``cycles`` (the feature's noise correlation) matter only to a model
    with Tx elements (module docstring)."""
    c_mm_s = velocity_m_s * MM_PER_M
    rel = grid.angle_deg[None, :] - rx_angle_deg
    n_pix = grid.shape[0] * grid.shape[1]
    groups, idxs, ws = [], [], []
    weight_sq = np.zeros((coherence_groups(model), n_pix))
    for family, length, weight in scatter_paths(model, grid.axial_mm[:, None], rel, rx_angle_deg):
        k = np.floor((length.ravel() / c_mm_s - t0_s) * fs_hz + 0.5)
        inside = (k >= 0) & (k < n_samples)
        if not inside.any():
            continue
        w = np.ascontiguousarray(weight.ravel() ** power, dtype=np.float32)
        groups.append(family)
        idxs.append(np.where(inside, k, n_samples).astype(np.int32))
        ws.append(w)
        weight_sq[family] += np.where(inside, np.square(w, dtype=np.float64), 0.0)
    table = GatherTable(
        np.asarray(groups, dtype=np.int64),
        np.stack(idxs) if idxs else np.zeros((0, n_pix), np.int32),
        np.stack(ws) if ws else np.zeros((0, n_pix), np.float32),
        weight_sq,
    )
    if model.elements and idxs:
        correlation = analytic_noise_correlation(fs_hz, excitation_hz, cycles)
        table = GatherTable(table.groups, table.idx, table.w,
                            coherent_energy(table.groups, table.idx, table.w, correlation, weight_sq.shape[0],
                                            n_samples))
    for arr in (table.groups, table.idx, table.w, table.weight_sq):
        arr.setflags(write=False)
    return table


TABLE_CACHE_BYTES = 1 << 30  # gather tables kept per process: ~400 of a 16-ring's (2.6 MB), ~16 of an 8-ring's (62 MB)
_tables: LRUCache = LRUCache(maxsize=TABLE_CACHE_BYTES, getsizeof=lambda table: table.nbytes)
# Least recently used first out, by bytes, not by count: a gateway's nodes each keep their geometry's
# tables while they fit; a table larger than the whole budget is built and used, not kept.
_cached_table = cached(_tables, lock=threading.Lock())(build_table)

# A grid's sums over its receivers, kept the same way (by bytes: a receiver mask that changes, a
# node whose channel comes and goes, makes a new entry; 32 by count were 0.8 GB of coarse 16-ring
# Gram inverses in double, or 12 GB of 1 mm x 1 deg ones).
GRAM_CACHE_BYTES = 1 << 30  # Gram whitenings: ~80 coarse 16-ring maps' with end echoes (13 MB), five 1 mm maps' (0.2 GB)
WEIGHT_CACHE_BYTES = 1 << 28  # per-group weight sums: ~90 coarse 16-ring maps' (2.8 MB), six 1 mm maps' (42 MB)
_gram_whitenings: LRUCache = LRUCache(maxsize=GRAM_CACHE_BYTES, getsizeof=lambda whitening: whitening.nbytes)
_weight_sums: LRUCache = LRUCache(maxsize=WEIGHT_CACHE_BYTES, getsizeof=lambda sums: sum(a.nbytes for a in sums))


def _rolls_onto_itself(model: PathModel, shift_deg: float) -> bool:
    """Does turning the pipe by ``shift_deg`` leave the model's Tx elements where they were (always, for a plane wave)?"""
    if not model.elements:
        return True
    circ = model.circumference_mm
    arcs = np.mod(np.array(model.tx_arcs_mm), circ)
    moved = np.mod(arcs + shift_deg * circ / 360.0, circ)
    gap = np.abs(moved[:, None] - arcs[None, :])
    return bool(np.all(np.min(np.minimum(gap, circ - gap), axis=1) < 1e-6))


def _receiver_plan(grid: Grid, rx_angles_deg: np.ndarray, model: PathModel) -> list[tuple[float, int]]:
    """(table angle, roll in pixels) per receiver: on a grid round the whole pipe, a receiver a whole
    number of angle steps from an earlier table's angle shares that table, turned (with Tx elements:
    only where the turn maps the elements onto themselves); the others get their own. A 16-ring at
    22.5 deg on a 1 deg grid: two tables (0 and 22.5 deg), not one and eight."""
    tables: list[float] = []
    plan = []
    for angle in (float(a) for a in rx_angles_deg):
        for ref in tables if grid.wraps_in_angle else ():
            steps = (angle - ref) / grid.angle_step_deg
            if abs(steps - round(steps)) < 1e-9 and _rolls_onto_itself(model, angle - ref):
                plan.append((ref, round(steps) % grid.angle_count))
                break
        else:
            tables.append(angle)
            plan.append((angle, 0))
    return plan


def _add_rolled(total: np.ndarray, part: np.ndarray, shift: int) -> None:
    """``total += np.roll(part, shift, axis=-1)`` without the rolled copy (a joint map's first Gram sum
    rolls [G, G, n_axial, n_angle] per receiver: the copies were a third of its time)."""
    if shift % part.shape[-1] == 0:
        total += part
        return
    shift %= part.shape[-1]
    total[..., shift:] += part[..., :-shift]
    total[..., :shift] += part[..., -shift:]


def _turns_by_table(plan: tuple[tuple[float, int], ...], mask: tuple[bool, ...]) -> dict[float, list[int]]:
    """Per table angle of ``_receiver_plan``, the turns of the healthy receivers that share it."""
    turns: dict[float, list[int]] = {}
    for (angle, roll), healthy in zip(plan, mask, strict=True):
        if healthy:
            turns.setdefault(angle, []).append(roll)
    return turns


def _add_turns(total: np.ndarray, part: np.ndarray, turns: list[int]) -> None:
    """``total += sum over turns t of np.roll(part, t, axis=-1)``. Turns that go round the pipe in k
    equal steps (a full ring's receivers sharing one table) add the same ``part`` folded: each pixel
    gets the sum over its k images, period n / k, so ``part`` is read once instead of k times."""
    n, k = part.shape[-1], len(turns)
    if k > 1 and n % k == 0 and total.flags.c_contiguous:
        period = n // k
        if sorted(t % n for t in turns) == sorted((turns[0] + i * period) % n for i in range(k)):
            fold = part.reshape(part.shape[:-1] + (k, period)).sum(axis=-2)
            total.reshape(total.shape[:-1] + (k, period))[...] += np.roll(fold, turns[0] % period, axis=-1)[..., None, :]
            return
    for turn in turns:
        _add_rolled(total, part, turn)


@cached(_weight_sums, lock=threading.Lock())
def _weight_sq_total(grid: Grid, plan: tuple[tuple[float, int], ...], model: PathModel, velocity_m_s: float,
                     t0_s: float, fs_hz: float, n_samples: int, power: int, excitation_hz: float, cycles: int,
                     mask: tuple[bool, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Per group, the sum over the healthy receivers of their rolled ``weight_sq`` [n_groups, n_axial, n_angle],
    and its ``_reciprocal``."""
    total = np.zeros((coherence_groups(model),) + grid.shape)
    for angle, turns in _turns_by_table(plan, mask).items():
        table = _cached_table(grid, angle, model, velocity_m_s, t0_s, fs_hz, n_samples, power, excitation_hz, cycles)
        _add_turns(total, table.weight_sq.reshape(total.shape), turns)
    inverse = _reciprocal(total)
    total.setflags(write=False)
    inverse.setflags(write=False)
    return total, inverse


def gram_whitening(gram: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Each pixel's cross-Gram [G, G, ...] with GRAM_RIDGE on its diagonal, as the whitening ``joint_power``
    reads (``pack_lower``: [2, G (G + 1) / 2, n_pixels] of ``dtype``): W = L^-1, L the Cholesky factor of
    the ridged Gram (M = L L^H), so that W^H W = M^-1 and |W b|^2 = b^H M^-1 b.

    ``gram`` itself gets the ridge (callers pass a sum they drop): no ridged copy of it is made."""
    stacked = np.moveaxis(gram, (0, 1), (-2, -1))
    diagonal = np.arange(stacked.shape[-1])
    empty = stacked[..., diagonal, diagonal].real.max(axis=-1) <= 0  # no path to the pixel: nothing to whiten
    ridge = _add_ridge(stacked)
    try:
        lower = np.linalg.cholesky(stacked)
    except np.linalg.LinAlgError:  # a sum rounded indefinite beyond the ridge: its eigenvalues floored at the ridge
        values, vectors = np.linalg.eigh(stacked)
        floored = np.maximum(values, ridge[..., None])
        lower = np.linalg.cholesky((vectors * floored[..., None, :]) @ np.conj(np.swapaxes(vectors, -1, -2)))
    factors = np.linalg.inv(lower)
    factors[empty] = 0.0  # (1 / sqrt of the ridge's floor would overflow single precision; its sums are 0)
    return pack_lower(factors, dtype)


def _add_ridge(stacked: np.ndarray) -> np.ndarray:
    """Add GRAM_RIDGE x each [..., G, G] Gram's largest diagonal term (at least a tiny absolute one) to
    its diagonal, in place (no [..., G, G] ridge term is built); the ridge added to each [...]."""
    diagonal = np.arange(stacked.shape[-1])
    ridge = GRAM_RIDGE * np.maximum(stacked[..., diagonal, diagonal].real.max(axis=-1), 1e-300)
    stacked[..., diagonal, diagonal] += ridge[..., None]
    return ridge


def _with_ridge(stacked: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of the [..., G, G] Grams with the ridge of ``_add_ridge`` on its diagonal."""
    out = np.array(stacked, order="C")
    _add_ridge(out)
    return out


@cached(_gram_whitenings, lock=threading.Lock())
def _gram_whitening_total(grid: Grid, plan: tuple[tuple[float, int], ...], model: PathModel, velocity_m_s: float,
                          t0_s: float, fs_hz: float, n_samples: int, power: int, excitation_hz: float, cycles: int,
                          mask: tuple[bool, ...], burst: tuple[float, int]) -> np.ndarray:
    """The whitening of the groups' cross-Gram summed over the healthy receivers, packed for each of the
    grid's pixels (``gram_whitening``; a plane-wave model's: one path per group and receiver).
    ``burst``: (excitation_hz, cycles) of the feature.

    Summed and factored GRAM_BLOCK_PIXELS at a time (whole rings of pixels, so that a shared table's
    turn round the pipe stays inside the block), each table's Gram computed once per block for all
    the receivers that share it (``_add_turns``): a 1 mm x 1 deg map's Grams are ~0.75 GB, and with
    the sum, a receiver's and the inverse alive together the first 16-ring ``analyze`` of a record
    with end echoes peaked at 2.9 GB; then 0.92 GB, of which the packed inverse (double) kept was 0.39,
    the packed whitening (single) kept now 0.2 (docs/benchmarks.md)."""
    n_groups = coherence_groups(model)
    covariance = analytic_noise_covariance(fs_hz, *burst)
    tables = [(_cached_table(grid, angle, model, velocity_m_s, t0_s, fs_hz, n_samples, power, excitation_hz, cycles),
               turns) for angle, turns in _turns_by_table(plan, mask).items()]
    n_axial, n_angle = grid.shape
    whitening = np.empty((2, n_groups * (n_groups + 1) // 2, n_axial * n_angle), dtype=np.float32)
    rows = max(1, GRAM_BLOCK_PIXELS // n_angle)  # the rolls turn the pipe: a block is whole rings of pixels
    for first in range(0, n_axial, rows):
        block = np.zeros((n_groups, n_groups, min(rows, n_axial - first), n_angle), dtype=np.complex128)
        pixels = slice(first * n_angle, first * n_angle + block.shape[2] * n_angle)
        for table, turns in tables:
            gram = cross_gram(table.groups, table.idx[:, pixels], table.w[:, pixels], covariance, n_groups, n_samples)
            _add_turns(block, gram.reshape(block.shape), turns)  # a shared table's Gram, once for its receivers
        whitening[:, :, pixels] = gram_whitening(block)
    whitening.setflags(write=False)
    return whitening


def _check_arguments(feature: np.ndarray, scene: Scene, normalise: str) -> None:
    if feature.ndim != 2 or feature.shape[0] != scene.n_rx:
        raise MultipathError(f"{scene.n_rx} receiver angles for feature rows of shape {feature.shape}")
    if normalise not in NORMALISATIONS:
        raise MultipathError(f"normalise must be one of {NORMALISATIONS}")


def _geometry(scene: Scene, n_samples: int) -> tuple[PathModel, float, float, float, int, int, float, int]:
    """What a gather table depends on besides the grid and the receiver angle (the table cache's key)."""
    elements = scene.model.elements
    return (scene.model, scene.velocity_m_s, scene.t0_s, scene.fs_hz, n_samples, scene.power,
            scene.excitation_hz if elements else 0.0, scene.cycles if elements else 0)


def multipath_pixels(feature: np.ndarray, scene: Scene, *, normalise: str = "snr") -> np.ndarray:
    """The all-paths map [n_axial, n_angle] on ``scene.grid`` of a feature [n_rx, n_samples] (fast gather);
    complex: coherent.

    Gather tables are cached per geometry (a node's map grid), so use this for a node's
    recurring grid and ``local_multipath_pixels`` for one-off small grids. The feature is
    gathered and summed in single precision (complex64/float32: half the memory traffic;
    imaging/gather.py). Relative error ~1e-6 of the map's scale.
    """
    feature = np.asarray(feature)
    _check_arguments(feature, scene, normalise)
    grid, mask = scene.grid, scene.rx_mask
    coherent = np.iscomplexobj(feature)
    n_rx, n = feature.shape
    geometry = _geometry(scene, n)
    padded = np.zeros((n_rx, n + 1), dtype=np.complex64 if coherent else np.float32)
    padded[:, :n] = feature
    plan = tuple(_receiver_plan(grid, scene.rx_angles_deg, scene.model))
    total = np.zeros((coherence_groups(scene.model),) + grid.shape, dtype=padded.dtype)
    for m, (angle, roll) in enumerate(plan):
        if mask[m]:
            table = _cached_table(grid, angle, *geometry)
            accumulate(total, padded[m], table.groups, table.idx, table.w, roll)
    healthy = tuple(bool(x) for x in mask)
    weight_sq, inverse = _weight_sq_total(grid, plan, *geometry, healthy)
    whitening = (_gram_whitening_total(grid, plan, *geometry, healthy, (scene.excitation_hz, scene.cycles))
                 if coherent and scene.joint_groups and not scene.model.elements else None)
    return _combine(total, weight_sq, normalise, inverse, whitening)


def local_multipath_pixels(feature: np.ndarray, scene: Scene, *, normalise: str = "snr",
                           compiled: bool = True) -> np.ndarray:
    """The same map as ``multipath_pixels`` for a small one-off ``scene.grid`` (a peak's neighbourhood, one pixel).

    Nothing is cached but, for ``scene.joint_groups``, the grid's Gram whitening: every receiver's paths to every pixel are computed here in double
    precision and the feature gathered directly, by the compiled kernel of imaging/gather.py
    (``compiled`` and numba installed) or in numpy. Cost grows as n_rx x n_paths x n_pixels:
    keep the grid to a few hundred pixels.
    """
    feature = np.asarray(feature)
    _check_arguments(feature, scene, normalise)
    grid, model, rx_angles_deg, power = scene.grid, scene.model, scene.rx_angles_deg, scene.power
    coherent = np.iscomplexobj(feature)
    rows = np.flatnonzero(scene.rx_mask).astype(np.int64)
    n_groups = coherence_groups(model)
    groups = np.zeros((n_groups,) + grid.shape, dtype=np.complex128 if coherent else np.float64)
    weight_sq = np.zeros((n_groups,) + grid.shape)
    c_mm_s = scene.velocity_m_s * MM_PER_M
    if rows.size and compiled and local_sums_compiled is not None and not model.elements:
        families = model.families()
        offset, sign, image, factor = (np.array([getattr(f, name) for f in families], dtype=np.float64)
                                       for name in ("in_offset_mm", "in_sign", "rx_image_mm", "factor"))
        data = np.ascontiguousarray(feature, dtype=np.complex128 if coherent else np.float64)
        local_sums_compiled(data, rows, rx_angles_deg.copy(), np.ascontiguousarray(grid.axial_mm),
                            np.ascontiguousarray(grid.angle_deg), offset, sign, image, factor, model.wraps,
                            float(model.circumference_mm), float(model.wavelength_mm), bool(model.polarization),
                            float(c_mm_s), scene.t0_s, scene.fs_hz, int(power), groups, weight_sq)
    elif rows.size:  # numpy; always for a model with Tx elements (the compiled kernel has no element images)
        groups, weight_sq = _local_numpy_sums(feature, scene, rows)
    whitening = (_local_gram_whitening(grid, model, tuple(float(a) for a in rx_angles_deg[rows]), scene.velocity_m_s,
                                       scene.t0_s, scene.fs_hz, feature.shape[1], int(power), scene.excitation_hz,
                                       scene.cycles)
                 if coherent and scene.joint_groups and not model.elements else None)
    return _combine(groups, weight_sq, normalise, whitening=whitening)


@lru_cache(maxsize=LOCAL_GRAM_CACHE)
def _local_gram_whitening(grid: Grid, model: PathModel, rx_angles_deg: tuple[float, ...], velocity_m_s: float,
                          t0_s: float, fs_hz: float, n: int, power: int, excitation_hz: float,
                          cycles: int) -> np.ndarray:
    """``_gram_whitening_total`` for a small grid (plane-wave model; the healthy receivers' angles), computed
    directly. Cached: a node's records of one defect refine their peaks on the same small grids."""
    c_mm_s = velocity_m_s * MM_PER_M
    n_groups = coherence_groups(model)
    total = np.zeros((n_groups, n_groups, grid.shape[0] * grid.shape[1]), dtype=np.complex128)
    covariance = analytic_noise_covariance(fs_hz, excitation_hz, cycles)
    for angle in rx_angles_deg:
        rel = grid.angle_deg[None, :] - angle
        family, length, weight = stacked_paths(model, grid.axial_mm[:, None], rel, angle)
        length, weight = np.broadcast_arrays(length, weight)
        k = np.floor((length / c_mm_s - t0_s) * fs_hz + 0.5).reshape(family.size, -1)
        inside = (k >= 0) & (k < n)
        total += cross_gram(family, np.where(inside, k, n).astype(np.int64),
                            (weight ** power).reshape(family.size, -1), covariance, n_groups, n)
    whitening = gram_whitening(total.reshape((n_groups, n_groups) + grid.shape), np.float64)  # as exact as the sums
    whitening.setflags(write=False)
    return whitening


def _local_numpy_sums(feature: np.ndarray, scene: Scene, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``local_multipath_pixels``' group sums and summed squared weights, vectorised over receivers and paths.

    With Tx elements a group holds several paths of one receiver, whose noise is correlated: their
    energy is ``coherent_energy``'s; otherwise each group has one path per receiver and it is sum w^2."""
    grid, model, power = scene.grid, scene.model, scene.power
    n = feature.shape[1]
    c_mm_s = scene.velocity_m_s * MM_PER_M
    n_groups = coherence_groups(model)
    rel = grid.angle_deg[None, None, :] - scene.rx_angles_deg[rows, None, None]
    family, length, weight = stacked_paths(model, grid.axial_mm[None, :, None], rel,
                                           scene.rx_angles_deg[rows, None, None])  # [P, n_rx, n_ax, n_an]
    k = np.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5)
    inside = (k >= 0) & (k < n)
    w = np.where(inside, weight**power, 0.0)
    samples = feature[rows[None, :, None, None], np.where(inside, k, 0).astype(np.intp)]
    groups = np.zeros((n_groups,) + grid.shape, dtype=np.result_type(feature.dtype, np.float64))
    np.add.at(groups, family, np.sum(w * samples, axis=1))
    weight_sq = np.zeros((n_groups,) + grid.shape)
    if not model.elements:
        weight_sq[family] += np.sum(w * w, axis=1)  # one path per group: ``family`` has no repeats
        return groups, weight_sq
    idx = np.where(inside, k, n).astype(np.int32).reshape(family.size, -1)
    correlation = analytic_noise_correlation(scene.fs_hz, scene.excitation_hz, scene.cycles)
    energy = coherent_energy(family, idx, w.reshape(family.size, -1), correlation, n_groups, n)
    return groups, energy.reshape((n_groups, rows.size) + grid.shape).sum(axis=1)


def literal_multipath_pixels(feature: np.ndarray, scene: Scene, *, normalise: str = "snr") -> np.ndarray:
    """The same map pixel by pixel, receiver by receiver, path by path: the test oracle."""
    feature = np.asarray(feature)
    grid, model, power = scene.grid, scene.model, scene.power
    coherent = np.iscomplexobj(feature)
    n_rx, n = feature.shape
    c_mm_s = scene.velocity_m_s * MM_PER_M
    n_fam = coherence_groups(model)
    correlation = analytic_noise_correlation(scene.fs_hz, scene.excitation_hz, scene.cycles)
    covariance = analytic_noise_covariance(scene.fs_hz, scene.excitation_hz, scene.cycles)
    joint = coherent and scene.joint_groups and not model.elements  # the groups projected on jointly (their cross-Gram)
    out = np.zeros(grid.shape)
    for i, z in enumerate(grid.axial_mm):
        for j, theta in enumerate(grid.angle_deg):
            sums = [0j] * n_fam
            weight_sq = [0.0] * n_fam
            gram = np.zeros((n_fam, n_fam), dtype=complex)
            for m in range(n_rx):
                if not scene.rx_mask[m]:
                    continue
                rx = float(scene.rx_angles_deg[m])
                taken: list[list[tuple[int, float]]] = [[] for _ in range(n_fam)]
                for family, length, w in scalar_paths(model, float(z), float(theta) - rx, rx):
                    k = math.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5)
                    if not 0 <= k < n:
                        continue
                    sums[family] += w**power * complex(feature[m, k])
                    taken[family].append((k, w**power))
                for family, members in enumerate(taken):
                    for ka, wa in members:  # correlated noise of nearby samples (only Tx elements put them there)
                        for kb, wb in members:
                            lag = abs(ka - kb)
                            weight_sq[family] += wa * wb * (1.0 if lag == 0 else
                                                            float(correlation[lag]) if lag < correlation.size else 0.0)
                if joint:
                    paths = [(f, k, w) for f, members in enumerate(taken) for k, w in members]
                    for fa, ka, wa in paths:
                        for fb, kb, wb in paths:
                            lag = kb - ka
                            c = complex(covariance[abs(lag)]) if abs(lag) < covariance.size else 0j
                            gram[fa, fb] += wa * wb * (c if lag >= 0 else c.conjugate())
            total_sq = sum(weight_sq)
            if total_sq <= 0:
                continue
            if joint:
                b = np.array(sums)
                quadratic = float((b.conj() @ np.linalg.inv(_with_ridge(gram)) @ b).real)
                snr = math.sqrt(max(quadratic, 0.0) / n_fam)
                out[i, j] = snr if normalise == "snr" else snr * math.sqrt(n_fam) / math.sqrt(total_sq)
            elif coherent:
                snr = math.sqrt(sum(abs(s) ** 2 / q for s, q in zip(sums, weight_sq, strict=True) if q > 0) / n_fam)
                out[i, j] = snr if normalise == "snr" else snr * math.sqrt(n_fam) / math.sqrt(total_sq)
            else:
                weighted = sum(s.real for s in sums)
                out[i, j] = weighted / (math.sqrt(total_sq) if normalise == "snr" else total_sq)
    return out


def path_model_for(
    baseline: Measurement,
    *,
    wall_mm: float | None = None,
    model_ends: bool = True,
    polarization: bool = True,
    wraps: int = 2,
    elements: bool = True,
) -> PathModel:
    """The path model of a node from its (defect-free) baseline.

    Wrap length: the mid-wall circumference pi (OD - wall) when ``wall_mm`` is known, else the
    record's circumference. Pipe ends are modelled when the record gives the pipe length and
    the Tx ring position, with reflection coefficients measured from the baseline's own end
    echoes (imaging/arrivals.py), so an absorbing end drops its paths by itself. A Tx ring sparse
    enough to launch more than circumferential order 0 in the excitation's band (imaging/paths.py
    ``sparse_ring``) is modelled element by element when its baseline shows it (the element model
    explains the baseline clearly better than a plane wave, ELEMENTS_EVIDENCE; ``elements`` False:
    as a plane wave anyway); its end coefficients, and without ``wall_mm`` its wrap length, are
    then fitted to the baseline (imaging/ring_fit.py). Every fitted value is quantised, so that every baseline of a node
    gives the same model and shares its cached gather tables.
    """
    circumference = baseline.circumference_mm
    if wall_mm is not None:
        if not 0 < wall_mm < baseline.outer_diameter_mm / 2:
            raise MultipathError(f"wall_mm must be in (0, OD/2), got {wall_mm}")
        circumference -= math.pi * wall_mm
    wavelength = baseline.velocity_m_s * MM_PER_M / baseline.excitation_hz
    tx_arcs: tuple[float, ...] = ()
    near_end: float | None = None
    far_end: float | None = None
    if model_ends and baseline.pipe_length_mm is not None and baseline.tx_axial_mm is not None:
        near_end, far_end = -baseline.tx_axial_mm, baseline.pipe_length_mm - baseline.tx_axial_mm
    coefficients: tuple[float, float] | None = None
    if elements and sparse_ring(baseline.tx_angles_deg.size, circumference, baseline.velocity_m_s,
                                baseline.excitation_hz, baseline.cycles):
        # Order N arrives with the end echoes and its cut-off hangs on the wrap length: fit the ring's own
        # incident model to the baseline (imaging/ring_fit.py) for both, the wrap only when no wall is given.
        tx_arcs = tuple(float(a) * circumference / 360.0 for a in baseline.tx_angles_deg)
        plain = PathModel(baseline.tx_rx_distance_mm, circumference, wavelength, polarization=polarization,
                          tx_arcs_mm=tx_arcs)
        ring = fit_sparse_ring(baseline, plain, near_end, far_end, fit_wrap=wall_mm is None)
        if ring.unexplained <= ELEMENTS_EVIDENCE * ring.plane_unexplained:
            if wall_mm is None:
                circumference = round(ring.circumference_mm / WRAP_QUANTUM_MM) * WRAP_QUANTUM_MM
            tx_arcs = tuple(float(a) * circumference / 360.0 for a in baseline.tx_angles_deg)
            coefficients = (ring.near, ring.far)
        else:  # the baseline shows no order-N arrival (a plane wave explains it better): model one
            tx_arcs = ()
    if near_end is None or far_end is None:
        return PathModel(baseline.tx_rx_distance_mm, circumference, wavelength, polarization=polarization, wraps=wraps,
                         tx_arcs_mm=tx_arcs)
    if coefficients is None:
        coefficients = end_reflection_coefficients(baseline)
    # Quantised so every baseline of a node gives the same model, hence the same cached tables.
    near, far = (round(r / REFLECTION_QUANTUM) * REFLECTION_QUANTUM for r in coefficients)
    return PathModel(
        baseline.tx_rx_distance_mm,
        circumference,
        wavelength,
        near_end_mm=near_end,
        far_end_mm=far_end,
        near_reflection=near,
        far_reflection=far,
        polarization=polarization,
        wraps=wraps,
        tx_arcs_mm=tx_arcs,
    )


def residual_map(residual: np.ndarray, scene: Scene, *, normalise: str = "snr") -> DIMap:
    """The all-paths map on ``scene.grid`` of a residual [n_rx, n_samples] recorded in ``scene``."""
    pixels = multipath_pixels(residual_feature(residual, scene), scene, normalise=normalise)
    return DIMap(pixels, scene.grid, "multipath", scene.window_samples)


def compute_multipath_map(
    baseline: Measurement,
    current: Measurement,
    grid: Grid | None = None,
    *,
    feature: str = "analytic",
    model: PathModel | None = None,
    rx_mask: np.ndarray | None = None,
    normalise: str = "snr",
) -> DIMap:
    """The all-paths DI map of ``current`` against ``baseline`` (no temperature compensation here)."""
    check_compatible(baseline, current)
    scene = Scene.of(baseline, model or path_model_for(baseline), grid or Grid.default(current.tx_rx_distance_mm),
                     feature=feature, reference_amplitude_v=reference_amplitude(baseline), rx_mask=rx_mask)
    residual = baseline.traces.astype(np.float64) - current.traces.astype(np.float64)
    return residual_map(residual, scene, normalise=normalise)
