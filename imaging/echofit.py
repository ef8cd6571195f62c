"""Point scatterers' echoes fitted to a residual: one burst per modelled path, free amplitude and phase.

On every receiver, each path from each position contributes two columns: the Hann burst and
its quadrature twin, starting at the path's arrival sample and cut to the record. The
amplitudes of all columns are fitted jointly, per receiver, by least squares (normal
equations, minimum-norm split between columns that (nearly) coincide: singular values of the
Gram matrix below FIT_RCOND of the largest are dropped), and each position's fitted echoes
are returned separately.

``fit_echoes`` builds the Gram matrix from a table of the burst pair's partial products at
each lag (the columns are shifted, possibly cut, copies of two fixed shapes), sums only
each column's own samples for the right-hand side and the echoes (imaging/fitkernels.py:
compiled with numba, numpy fallback), and solves every receiver at once; ``literal_fit_echoes`` builds each column as
a full-length vector and solves receiver by receiver: the test oracle. ``fit_smooth_echoes``
shares each path's amplitude across the receivers, optionally as a circular harmonic of their
bearing (its oracle: ``literal_fit_smooth_echoes``). A model whose coherence groups hold several
paths (Tx elements, imaging/paths.py) is fitted with one amplitude per group instead
(``group_waves``: each group's paths synthesised together); the oracles take the same route
only for the plane-wave model.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from imaging.fitkernels import group_columns, normal_equations, synthesise
from imaging.paths import coherence_groups, element_scattering_cosines, scalar_paths, stacked_paths
from imaging.scatterers import disc_weights
from imaging.scene import Scene
from imaging.timing import MM_PER_M

FIT_RCOND = 1e-6  # relative cut-off on the Gram matrix's singular values (1e-3 on the design's)
EXTENT_STEP_WAVELENGTHS = 0.125  # an extended scatterer's parts lie at most this far apart (``extent_offsets_mm``)


def burst_pair(fs_hz: float, excitation_hz: float, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """The Hann burst and its quadrature twin (carrier shifted by 90 degrees): any carrier phase is a mix."""
    n = max(2, math.floor(cycles / excitation_hz * fs_hz) + 1)
    t = np.arange(n) / fs_hz
    window = 0.5 * (1.0 - np.cos(2.0 * math.pi * excitation_hz * t / cycles))
    phase = 2.0 * math.pi * excitation_hz * t
    return window * np.sin(phase), window * np.cos(phase)


@lru_cache(maxsize=2)
def _partial_products(fs_hz: float, excitation_hz: float, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """(shapes [2, L], table [2, 2, 2L - 1, L + 1]) with
    table[x, y, d + L - 1, u] = sum_{v < u} shape_x[v] shape_y[v - d] (shape_y zero outside [0, L)).

    Any Gram entry of two columns, however the record cuts them, is a difference of two entries
    (~22 MB at 85 kHz, 10 MHz; built once per excitation).
    """
    shapes = np.stack(burst_pair(fs_hz, excitation_hz, cycles))
    size = shapes.shape[1]
    padded = np.zeros((2, 3 * size))
    padded[:, size:2 * size] = shapes
    lags = np.arange(1 - size, size)
    # shifted[y, d, v] = shape_y[v - d]
    shifted = padded[:, size - lags[:, None] + np.arange(size)[None, :]]
    table = np.zeros((2, 2, lags.size, size + 1))
    table[..., 1:] = np.cumsum(shapes[:, None, None, :] * shifted[None, :, :, :], axis=-1)
    shapes.setflags(write=False)
    table.setflags(write=False)
    return shapes, table


def _start_samples(scene: Scene, length_mm: np.ndarray) -> np.ndarray:
    """The sample (int64) at which a burst that travelled ``length_mm`` starts in the scene's record."""
    return np.floor((length_mm / (scene.velocity_m_s * MM_PER_M) - scene.t0_s) * scene.fs_hz + 0.5).astype(np.int64)


def _arrival_samples(scene: Scene, positions: list[tuple[float, float]]) -> np.ndarray:
    """Burst start sample of every (receiver, position, path): int64 [n_rx, n_positions, n_paths]."""
    z = np.array([p[0] for p in positions], dtype=np.float64)
    rel = np.array([p[1] for p in positions], dtype=np.float64)[None, :] - scene.rx_angles_deg[:, None]
    _groups, length, _w = stacked_paths(scene.model, z[None, :], rel)  # [n_paths, n_rx, n_positions]
    return np.ascontiguousarray(_start_samples(scene, length).transpose(1, 2, 0))


def extent_offsets_mm(extent_mm: float, wavelength_mm: float) -> np.ndarray:
    """Where round the pipe (mm from its centre) the parts of a scatterer ``extent_mm`` wide lie: the centres of
    equal segments at most EXTENT_STEP_WAVELENGTHS long; the centre alone for no extent."""
    if not extent_mm > 0.0:
        return np.zeros(1)
    parts = max(2, math.ceil(extent_mm / (EXTENT_STEP_WAVELENGTHS * wavelength_mm)))
    return ((np.arange(parts) + 0.5) / parts - 0.5) * extent_mm


class _Parts(NamedTuple):
    """Every position's parts (``extent_offsets_mm``; one, the point itself, without an extent): per part its
    position (``owner``), its arc from the position's centre and its share of the position's amplitude."""

    owner: np.ndarray
    offset_mm: np.ndarray
    share: np.ndarray

    @classmethod
    def of(cls, scene: Scene, n_pos: int, extents_mm: Sequence[float] | None) -> _Parts:
        parts = [extent_offsets_mm(e, scene.wavelength_mm) for e in (extents_mm or [0.0] * n_pos)]
        return cls(np.concatenate([np.full(p.size, i) for i, p in enumerate(parts)]), np.concatenate(parts),
                   np.concatenate([np.full(p.size, 1.0 / p.size) for p in parts]))

    def paths(self, scene: Scene, positions: list[tuple[float, float]], rx_angle_deg: float | np.ndarray = 0.0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(z [1, part], rel [m, part], groups [P], length_mm and weight [P, m, part]) of every part along its
        position's legs (``stacked_paths``), each weight times the part's share."""
        z = np.array([p[0] for p in positions], dtype=np.float64)[self.owner][None, :]
        rel = np.array([p[1] for p in positions], dtype=np.float64)[self.owner][None, :] - scene.rx_angles_deg[:, None]
        groups, length, weight = stacked_paths(scene.model, z, rel, rx_angle_deg, self.offset_mm[None, :])
        return z, rel, groups, length, weight * self.share


def group_waves(scene: Scene, positions: list[tuple[float, float]], n: int,
                lags_rad: Sequence[float] | None = None, backward: Sequence[bool] | None = None,
                extents_mm: Sequence[float] | None = None, discs_mm: Sequence[float] | None = None) -> np.ndarray:
    """Each position's echo along each coherence group, as it reaches each receiver: [n_rx, n_pos, n_groups, 2, n]
    (burst and quadrature twin), the group's paths added with their weights and cut to the record.

    For a model whose groups hold several paths (a Tx ring modelled element by element,
    imaging/paths.py): its incident terms arrive close together and share one amplitude.
    ``lags_rad`` (one per position, default none): each path's carrier lags by lag (1 - cos psi),
    psi its scattering angle (``element_scattering_cosines``): a scatterer whose forward field lags
    its backward one, as a notch's does (docs/imaging.md, "A forward lag fitted on sparse rings").
    ``backward`` (one per position, default none): each path's weight times (1 - cos psi) / 2, a scatterer
    that sends nothing straight on and most straight back, as a thinning of the wall does to first order
    (docs/imaging.md, "A backward weight tried beside the lags on sparse rings").
    ``extents_mm`` (one per position, default none): a scatterer that long round the pipe, a line of points
    (``extent_offsets_mm``) of equal strength whose paths share their centre's groups: a notch wider round the
    pipe than a wavelength's fraction radiates as a line, not a point (docs/imaging.md, "A defect's extent round
    the pipe"). Any model, with or without Tx elements.
    ``discs_mm`` (one per position, default none; 0: none): each path's echo times a clamped disc's pattern of that
    radius, f(psi) / f(0) (imaging/scatterers.py ``disc_weights``; with a lag, both): a heavy mass (docs/imaging.md,
    "A strong scatterer on a sparse ring fitted as a clamped disc").
    Built by imaging/fitkernels.py ``group_columns`` (compiled; FFT convolution without numba).
    """
    t = _group_terms(scene, positions, n, lags_rad, backward, extents_mm, discs_mm)
    return group_columns(t.rx, t.pos, t.group, t.starts, t.c, t.s, t.shapes,
                         (scene.n_rx, len(positions), coherence_groups(scene.model), n))


class _Terms(NamedTuple):
    """``group_waves``' path terms that reach the record: per term its receiver, position, coherence group,
    start sample, in-phase and quadrature weights (``s`` None: no lag); and the burst pair [2, size]."""

    rx: np.ndarray
    pos: np.ndarray
    group: np.ndarray
    starts: np.ndarray
    c: np.ndarray
    s: np.ndarray | None
    shapes: np.ndarray


def _group_terms(scene: Scene, positions: list[tuple[float, float]], n: int, lags_rad: Sequence[float] | None,
                 backward: Sequence[bool] | None, extents_mm: Sequence[float] | None = None,
                 discs_mm: Sequence[float] | None = None) -> _Terms:
    """``group_waves``' path terms that reach the record (``_Terms``): every part of every position (its extent's
    ``extent_offsets_mm``) along every path, each part weighted 1 / parts."""
    shapes = np.stack(burst_pair(scene.fs_hz, scene.excitation_hz, scene.cycles))
    size = shapes.shape[1]
    parts = _Parts.of(scene, len(positions), extents_mm)
    rx = scene.rx_angles_deg[:, None]
    z, rel, groups, length, weight = parts.paths(scene, positions, rx)  # [P, m, part]
    k = _start_samples(scene, length)
    keep = (k < n) & (k + size > 0) & scene.rx_mask[None, :, None]
    p_idx, m_idx, part_idx = np.nonzero(keep)
    c, s = weight[keep], None
    lagged = lags_rad is not None and any(lag != 0.0 for lag in lags_rad)
    weighted = backward is not None and any(backward)
    disced = discs_mm is not None and any(r != 0.0 for r in discs_mm)
    if lagged or weighted or disced:
        cos_psi = element_scattering_cosines(scene.model, z, rel, rx, parts.offset_mm[None, :])
    if weighted:
        c = c * np.where(np.asarray(backward, dtype=bool)[parts.owner][None, None, :], 0.5 * (1.0 - cos_psi), 1.0)[keep]
    if lagged or disced:
        pattern = np.ones(cos_psi.shape, dtype=np.complex128)  # [P, m, part]
        if lagged:
            pattern *= np.exp(1j * np.asarray(lags_rad, dtype=np.float64)[parts.owner][None, None, :] * (1.0 - cos_psi))
        if disced:
            radius = np.asarray(discs_mm, dtype=np.float64)[parts.owner]
            for r in np.unique(radius[radius != 0.0]):
                on = radius == r
                pattern[:, :, on] *= disc_weights(float(r), scene.wavelength_mm, cos_psi[:, :, on])
        c, s = c * pattern.real[keep], c * pattern.imag[keep]
    return _Terms(m_idx, parts.owner[part_idx], groups[p_idx], k[keep], c, s, shapes)


def _bearing_basis(scene: Scene, positions: list[tuple[float, float]], orders: int) -> np.ndarray:
    """[n_rx, n_pos, 1 + 2 orders]: 1, cos k d, sin k d (k = 1..orders) of each receiver's bearing d from each position."""
    rel = np.array([p[1] for p in positions], dtype=np.float64)[None, :] - scene.rx_angles_deg[:, None]
    bearing = np.deg2rad(rel)  # [m, pos]
    basis = [np.ones_like(bearing)]
    for k in range(1, orders + 1):
        basis += [np.cos(k * bearing), np.sin(k * bearing)]
    return np.stack(basis, axis=-1)


def _fit_group_waves(residual: np.ndarray, scene: Scene, positions: list[tuple[float, float]], orders: int,
                     shared: bool, lags_rad: Sequence[float] | None = None,
                     backward: Sequence[bool] | None = None,
                     extents_mm: Sequence[float] | None = None,
                     discs_mm: Sequence[float] | None = None) -> list[np.ndarray]:
    """``fit_smooth_echoes`` (``shared``) or ``fit_echoes`` with one unknown per coherence group instead of per
    path, on ``group_waves`` (``lags_rad``: its forward lags; ``backward``: its backward weight; ``extents_mm``:
    its extents; ``discs_mm``: its clamped discs): the fit for a model with Tx elements."""
    n_rx, n = residual.shape
    n_pos, n_groups = len(positions), coherence_groups(scene.model)
    t = _group_terms(scene, positions, n, lags_rad, backward, extents_mm, discs_mm)
    if not t.starts.size:  # no echo of any position reaches the record: nothing to fit
        return [np.zeros((n_rx, n)) for _ in positions]
    # Only the columns (position, group) some path reaches the record along, over the samples those paths
    # reach: a group with no path in the record on any receiver is a zero row and column of every Gram below,
    # which the pseudo-inverse maps to zero (its cut-off is relative to the largest eigenvalue, which they do
    # not change), and samples no path reaches add nothing. Left out, the fit is the same and its matrices
    # smaller (a sparse ring's two-defect fit: a third of 216 columns, a fifth of the samples).
    live, column = np.unique(t.pos * n_groups + t.group, return_inverse=True)
    span = slice(max(int(t.starts.min()), 0), min(int(t.starts.max()) + t.shapes.shape[1], n))
    waves = group_columns(t.rx, np.zeros_like(t.pos), column, t.starts - span.start, t.c, t.s, t.shapes,
                          (n_rx, 1, live.size, span.stop - span.start))  # [m, 1, live, 2, span]
    columns = waves.reshape(n_rx, 2 * live.size, -1)  # [m, a, span], a = (live column, shape)
    owner = np.repeat(live // n_groups, 2)  # each column's position
    gram = np.einsum("man,mbn->mab", columns, columns, optimize=True)
    rhs = np.einsum("man,mn->ma", columns, residual[:, span], optimize=True)
    if not shared:
        coef = np.einsum("mab,mb->ma", np.linalg.pinv(gram, rtol=FIT_RCOND, hermitian=True), rhs)
    else:
        wc = _bearing_basis(scene, positions, orders)[:, owner]  # [m, a, K]
        n_basis = wc.shape[-1]
        big_gram = np.einsum("mak,mab,mbl->akbl", wc, gram, wc, optimize=True).reshape(owner.size * n_basis, -1)
        big_rhs = np.einsum("mak,ma->ak", wc, rhs).ravel()
        unknowns = np.linalg.pinv(big_gram, rtol=FIT_RCOND, hermitian=True) @ big_rhs
        coef = np.einsum("mak,ak->ma", wc, unknowns.reshape(owner.size, n_basis))
    fitted = [np.zeros((n_rx, n)) for _ in positions]
    for p in range(n_pos):
        own = owner == p
        fitted[p][:, span] = np.einsum("man,ma->mn", columns[:, own], coef[:, own], optimize=True)
    return fitted


def fit_echoes(residual: np.ndarray, scene: Scene, positions: list[tuple[float, float]]) -> list[np.ndarray]:
    """Joint least-squares fit, on each of the scene's healthy receivers, of point scatterers' echoes at
    ``positions`` (axial_mm, angle_deg), along the scene's modelled paths.

    Returns one fitted echo array [n_rx, n] per position (their sum is the full fit). Fitting
    the scatterers together keeps one from absorbing another's echoes where they overlap.
    With Tx elements, one amplitude per receiver and coherence group (``group_waves``).
    """
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    mask = scene.rx_mask
    if not positions:
        return []
    if scene.model.elements:
        return _fit_group_waves(residual, scene, positions, 0, shared=False)
    shapes, table = _partial_products(scene.fs_hz, scene.excitation_hz, scene.cycles)
    size = shapes.shape[1]
    n_pos = len(positions)
    # Columns per receiver: (position, path, shape), shape fastest; those inside the record first.
    starts = np.repeat(_arrival_samples(scene, positions).reshape(n_rx, -1), 2, axis=1)
    kind = np.tile(np.array([0, 1]), (n_rx, starts.shape[1] // 2))
    owner = np.repeat(np.arange(n_pos), starts.shape[1] // n_pos)[None, :].repeat(n_rx, axis=0)
    valid = (starts < n) & (starts + size > 0) & mask[:, None]
    order = np.argsort(~valid, axis=1, kind="stable")[:, : max(1, int(valid.sum(axis=1).max()))]
    starts, kind, owner, valid = (np.take_along_axis(x, order, axis=1) for x in (starts, kind, owner, valid))
    starts = np.where(valid, starts, 0)
    gram, rhs = normal_equations(residual, starts, kind, valid, shapes, table)
    coef = np.einsum("mab,mb->ma", np.linalg.pinv(gram, rtol=FIT_RCOND, hermitian=True), rhs)
    # Each position's echoes: every column's coefficient times its shape, added at its samples.
    return list(synthesise(coef, starts, kind, valid, owner, shapes, n_pos, n))


def literal_fit_echoes(residual: np.ndarray, scene: Scene, positions: list[tuple[float, float]]) -> list[np.ndarray]:
    """The same fit with every column written out in full, receiver by receiver: the test oracle."""
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    mask = scene.rx_mask
    in_phase, quadrature = burst_pair(scene.fs_hz, scene.excitation_hz, scene.cycles)
    c_mm_s = scene.velocity_m_s * MM_PER_M
    fitted = [np.zeros_like(residual) for _ in positions]
    for m in range(n_rx):
        if not mask[m]:
            continue
        columns, owner = [], []
        for p, (axial_mm, angle_deg) in enumerate(positions):
            rel = angle_deg - float(scene.rx_angles_deg[m])
            for _group, length, _w in scalar_paths(scene.model, axial_mm, rel):
                k = math.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5)
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
        coef, *_ = np.linalg.lstsq(design.T @ design, design.T @ residual[m], rcond=FIT_RCOND)
        owner_arr = np.asarray(owner)
        for p in range(len(positions)):
            sel = owner_arr == p
            if sel.any():
                fitted[p][m] = design[:, sel] @ coef[sel]
    return fitted


SMOOTH_ORDERS = 0  # Fourier orders of a path's amplitude over the receivers' bearings (0: one amplitude, the map's)


def fit_smooth_echoes(residual: np.ndarray, scene: Scene, positions: list[tuple[float, float]],
                      orders: int = SMOOTH_ORDERS, lags_rad: Sequence[float] | None = None,
                      backward: Sequence[bool] | None = None,
                      extents_mm: Sequence[float] | None = None,
                      discs_mm: Sequence[float] | None = None) -> list[np.ndarray]:
    """Like ``fit_echoes``, but each path's amplitude is shared by the receivers (the map's own model).

    The coherent map (imaging/multipath.py) scores a point scatterer with one complex amplitude
    per path group for all receivers, weighted by the path's expected amplitude w_mp. The fit
    here uses the same model, optionally with a pattern smooth in direction: on receiver m the
    echo along path p is w_mp sum_k (a_pk cos k d_m + b_pk sin k d_m) (burst and quadrature twin
    each), d_m the receiver's bearing from the scatterer, k = 0..``orders`` (default 0: one
    amplitude), fitted jointly over all receivers. ``orders=1`` follows a real scatterer's
    directional field; the multi-defect search (imaging/multidefect.py) uses it as the
    alternative a later peak must beat. The receivers' Gram blocks are combined per column with
    its K weights w_mp basis_k(d_m) (the mapping to unknowns is block-diagonal, K = 1 + 2 orders).
    ``fit_echoes`` gives every receiver its own
    amplitude for every path: on a 16-receiver ring that also absorbs another defect's echoes
    wherever they overlap one of this defect's many paths, so the weaker of two defects vanished
    with the stronger one's fit (full-wave dev set: a second notch of DI 0.15 left at 0.03).
    ``lags_rad``: each position's forward lag, ``backward``: whether its paths carry the backward weight
    (``group_waves``); a model with Tx elements only. ``extents_mm``: each position's extent round the pipe
    (``group_waves``), any model: on the plane-wave model each part of a line is a point of its own in the Gram
    matrix, its blocks then added into the line's (the parts share the line's unknowns). ``discs_mm``: each
    position's clamped disc radius (0: a point; ``group_waves``), a model with Tx elements only.
    """
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    if not positions:
        return []
    if scene.model.elements:
        return _fit_group_waves(residual, scene, positions, orders, shared=True, lags_rad=lags_rad, backward=backward,
                                extents_mm=extents_mm, discs_mm=discs_mm)
    if discs_mm is not None and any(r != 0.0 for r in discs_mm):
        raise ValueError("a clamped disc is fitted only for a model with Tx elements")
    if backward is not None and any(backward):
        raise ValueError("a backward weight is fitted only for a model with Tx elements")
    if lags_rad is not None and any(lag != 0.0 for lag in lags_rad):
        raise ValueError("a forward lag is fitted only for a model with Tx elements (a plane wave trades it "
                         "against the axial position)")
    shapes, table = _partial_products(scene.fs_hz, scene.excitation_hz, scene.cycles)
    size = shapes.shape[1]
    n_pos = len(positions)
    # A line (``extents_mm``) is fitted as its parts (``extent_offsets_mm``), each a point whose columns carry its
    # share of the line's amplitudes: the parts' Gram blocks are added into their line's below.
    parts = _Parts.of(scene, n_pos, extents_mm)
    owner_of, n_parts = parts.owner, parts.owner.size
    _z, _rel, _g, length, weight = parts.paths(scene, positions)  # [P, m, part]
    samples = np.ascontiguousarray(_start_samples(scene, length).transpose(1, 2, 0))  # [m, part, P]
    # A path whose burst lies outside the record on every receiver, for every position, has no
    # column anywhere (its unknowns would be zero): leave it out (most of a model's further turns
    # round the pipe and end echoes arrive after the record; the Gram matrix grows as their square).
    in_record = (samples < n) & (samples + size > 0) & scene.rx_mask[:, None, None]  # [m, part, P]
    inside = in_record.any(axis=(0, 1))
    samples, in_record, weight = samples[:, :, inside], in_record[:, :, inside], weight[inside]
    n_paths = samples.shape[2]
    basis_arr = _bearing_basis(scene, positions, orders)[:, owner_of]  # [m, part, K]: the line's centre's bearing
    n_basis = basis_arr.shape[-1]
    # Columns per receiver: (part, path, shape), shape fastest.
    starts = np.repeat(samples.reshape(n_rx, -1), 2, axis=1)
    kind = np.tile(np.array([0, 1]), (n_rx, starts.shape[1] // 2))
    valid = np.repeat(in_record.reshape(n_rx, -1), 2, axis=1)
    starts = np.where(valid, starts, 0)
    gram, rhs = normal_equations(residual, starts, kind, valid, shapes, table)
    owner = np.repeat(owner_of, n_paths * 2)[None, :].repeat(n_rx, axis=0)
    # Column (part, path, shape) on receiver m carries unknowns (position, path, shape, k) with weights
    # w_mp * basis_k(d_m): one row of K weights per column (K = 1: the constant alone, one amplitude per path).
    w = weight.transpose(1, 2, 0)  # [m, part, P]
    wc = np.repeat(w.reshape(n_rx, -1), 2, axis=1)[:, :, None] * np.repeat(
        np.repeat(basis_arr, n_paths, axis=1), 2, axis=1)  # [m, column, K]
    n_cols = n_parts * n_paths * 2
    if n_parts > n_pos:
        coef = _line_coefficients(gram, rhs, wc, owner_of, n_pos, n_paths)
    elif n_basis == 1:  # points, one amplitude per path: the mapping is diagonal, a column's weight w_mp
        big_gram = np.einsum("ma,mab,mb->ab", wc[..., 0], gram, wc[..., 0])
        unknowns = np.linalg.pinv(big_gram, rtol=FIT_RCOND, hermitian=True) @ np.einsum("ma,ma->a", wc[..., 0], rhs)
        coef = wc[..., 0] * unknowns[None, :]
    else:  # points: the mapping is block-diagonal
        big_gram = np.einsum("mak,mab,mbl->akbl", wc, gram, wc, optimize=True).reshape(n_cols * n_basis, -1)
        big_rhs = np.einsum("mak,ma->ak", wc, rhs).ravel()
        unknowns = np.linalg.pinv(big_gram, rtol=FIT_RCOND, hermitian=True) @ big_rhs
        coef = np.einsum("mak,ak->ma", wc, unknowns.reshape(n_cols, n_basis))
    return list(synthesise(coef, starts, kind, valid, owner, shapes, n_pos, n))



def _line_coefficients(gram: np.ndarray, rhs: np.ndarray, wc: np.ndarray, owner_of: np.ndarray, n_pos: int,
                       n_paths: int) -> np.ndarray:
    """``fit_smooth_echoes``' column coefficients [m, column] when some positions are lines: the columns
    (part, path, shape) of a line's parts share the line's unknowns (position, path, shape, k). The map M [m,
    column, unknown] holds each column's K weights ``wc`` [m, column, K]; the unknowns' normal equations are
    M^T G M and M^T r summed over the receivers (``gram`` [m, column, column], ``rhs`` [m, column])."""
    n_rx, n_cols, n_basis = wc.shape
    per_position = n_paths * 2
    column_unknown = np.repeat(owner_of, per_position) * per_position + np.tile(np.arange(per_position), owner_of.size)
    mapping = np.zeros((n_rx, n_cols, n_pos * per_position * n_basis))
    for k in range(n_basis):
        mapping[:, np.arange(n_cols), column_unknown * n_basis + k] = wc[:, :, k]
    flat = mapping.reshape(n_rx * n_cols, -1)
    big_gram = flat.T @ np.matmul(gram, mapping).reshape(n_rx * n_cols, -1)
    unknowns = np.linalg.pinv(big_gram, rtol=FIT_RCOND, hermitian=True) @ (flat.T @ rhs.ravel())
    return mapping @ unknowns


def literal_fit_smooth_echoes(residual: np.ndarray, scene: Scene, positions: list[tuple[float, float]],
                              orders: int = SMOOTH_ORDERS) -> list[np.ndarray]:
    """``fit_smooth_echoes`` with every unknown's column written out over all receivers: the test oracle."""
    residual = np.asarray(residual, dtype=np.float64)
    n_rx, n = residual.shape
    in_phase, quadrature = burst_pair(scene.fs_hz, scene.excitation_hz, scene.cycles)
    c_mm_s = scene.velocity_m_s * MM_PER_M
    columns: list[np.ndarray] = []
    owner: list[int] = []
    for p, (axial_mm, angle_deg) in enumerate(positions):
        per_receiver = [scalar_paths(scene.model, axial_mm, angle_deg - float(scene.rx_angles_deg[m]))
                        for m in range(n_rx)]
        for path in range(len(per_receiver[0])):
            for k in range(orders + 1):
                for harmonic in ((math.cos,) if k == 0 else (math.cos, math.sin)):
                    for shape in (in_phase, quadrature):
                        col = np.zeros((n_rx, n))
                        for m in range(n_rx):
                            if not scene.rx_mask[m]:
                                continue
                            _group, length, w = per_receiver[m][path]
                            bearing = math.radians(angle_deg - float(scene.rx_angles_deg[m]))
                            start = math.floor((length / c_mm_s - scene.t0_s) * scene.fs_hz + 0.5)
                            lo, hi = max(start, 0), min(start + shape.size, n)
                            if hi > lo:
                                col[m, lo:hi] = w * harmonic(k * bearing) * shape[lo - start:hi - start]
                        columns.append(col.ravel())
                        owner.append(p)
    fitted = [np.zeros_like(residual) for _ in positions]
    if not columns:
        return fitted
    design = np.stack(columns, axis=1)
    coef = np.linalg.pinv(design.T @ design, rtol=FIT_RCOND, hermitian=True) @ (design.T @ residual.ravel())
    owner_arr = np.asarray(owner)
    for p in range(len(positions)):
        sel = owner_arr == p
        fitted[p] = (design[:, sel] @ coef[sel]).reshape(n_rx, n)
    return fitted
