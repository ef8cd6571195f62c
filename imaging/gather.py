"""Inner loops of the all-paths map (imaging/multipath.py), compiled with numba when it is installed.

1. The cached-table gather: add one receiver's weighted feature samples into the group sums.

    out[g(p), i, (j + roll) % n_angle] += w[p, i n_angle + j] * row[idx[p, i n_angle + j]]

for every path p of a receiver's gather table (imaging/multipath.py builds the tables). Two
implementations of the same sum: a compiled numba kernel (one pass, no temporaries, the roll
applied to the output index instead of rolling a map) and a numpy fallback (take, multiply,
two slice-adds). ``accumulate`` uses the kernel when numba is importable and
PIPESENTRY_NUMBA is not "0"; tests hold the two equal. The kernels are compiled eagerly for
the two signatures used (complex64 and float32 features) when this module is imported:
~1-2 s once per machine, then loaded from numba's on-disk cache (tens of ms).

2. ``local_sums_compiled``: a small grid's group sums and squared weights computed path by
path with the literal oracle's scalar math (hypot as the square root of a sum of squares,
within an ulp) (imaging/multipath.py
``local_multipath_pixels`` falls back to its vectorised numpy form without numba).

3. ``coherent_energy``: per coherence group, the noise variance of the sum of a receiver's
weighted samples when several of them fall close together (an element-by-element incident wave,
imaging/paths.py): sum over pairs of paths in the group of w_a w_b r(|k_a - k_b|), r the feature's
noise correlation (imaging/arrivals.py ``analytic_noise_correlation``); paths outside the record
(k = n) count nothing. Compiled with numba, numpy fallback; tests hold them equal.

5. ``joint_power``: per pixel b^H M^-1 b = |W b|^2, b the groups' sums, M the cross-Gram (4) and W
its whitening (W^H W = M^-1, lower-triangular: the inverse of M's Cholesky factor), held as its
lower triangle (``pack_lower``; a map's full grid in single precision: a quarter of the bytes of the
whole inverse in double), block by block of pixels in real arithmetic the compiler vectorises.

4. ``cross_gram``: the same across groups, complex — the groups' cross-Gram of one receiver,
sum over pairs (a, b) of paths of w_a w_b C(k_b - k_a) into (group of a, group of b), C the
feature's complex noise covariance (imaging/arrivals.py ``analytic_noise_covariance``), which the
coherent map projects on jointly (imaging/multipath.py). Compiled with numba, numpy fallback.
"""
from __future__ import annotations

import math

import numpy as np

from imaging.jit import njit, numba_module


def accumulate_numpy(out: np.ndarray, row: np.ndarray, groups: np.ndarray, idx: np.ndarray, w: np.ndarray,
                     roll: int) -> None:
    """The sum above, in numpy: ``out`` [G, n_axial, n_angle] (``row``'s dtype) is updated in place."""
    n_angle = out.shape[2]
    roll = int(roll) % n_angle
    partial = np.zeros((out.shape[0], out.shape[1] * n_angle), dtype=row.dtype)
    tmp = np.empty(idx.shape[1], dtype=row.dtype)
    for p in range(idx.shape[0]):
        np.take(row, idx[p], out=tmp)
        tmp *= w[p]
        partial[groups[p]] += tmp
    partial = partial.reshape(out.shape)
    out[:, :, roll:] += partial[:, :, : n_angle - roll]
    if roll:
        out[:, :, :roll] += partial[:, :, n_angle - roll :]


def _accumulate_loops(out, row, groups, idx, w, roll):  # pragma: no cover - compiled by numba
    n_paths = idx.shape[0]
    n_axial, n_angle = out.shape[1], out.shape[2]
    roll = roll % n_angle
    split = n_angle - roll
    for p in range(n_paths):
        g = groups[p]
        for i in range(n_axial):
            base = i * n_angle
            for j in range(split):
                out[g, i, j + roll] += w[p, base + j] * row[idx[p, base + j]]
            for j in range(split, n_angle):
                out[g, i, j - split] += w[p, base + j] * row[idx[p, base + j]]


def _compile():
    numba = numba_module()
    if numba is None:
        return None
    t = numba.types
    tables = (t.Array(t.int64, 1, "C", readonly=True), t.Array(t.int32, 2, "C", readonly=True),
              t.Array(t.float32, 2, "C", readonly=True), t.int64)
    signatures = [
        t.void(t.complex64[:, :, ::1], t.complex64[::1], *tables),
        t.void(t.float32[:, :, ::1], t.float32[::1], *tables),
    ]
    return njit(numba, signatures, _accumulate_loops)


accumulate_compiled = _compile()


def compiled() -> bool:
    """True when the numba kernel is in use."""
    return accumulate_compiled is not None


def accumulate(out: np.ndarray, row: np.ndarray, groups: np.ndarray, idx: np.ndarray, w: np.ndarray,
               roll: int) -> None:
    """The module's sum, by the compiled kernel when available. Argument dtypes: ``out`` and ``row``
    complex64, or both float32 (single precision: sums of a few dozen terms, ~1e-7 relative);
    ``groups`` int64; ``idx`` int32 in [0, row.size); ``w`` float32."""
    if accumulate_compiled is not None:
        accumulate_compiled(out, row, groups, idx, w, int(roll))
    else:
        accumulate_numpy(out, row, groups, idx, w, roll)


def _local_loops(feature, rows, rx_angles_deg, axial_mm, angle_deg, offset, sign, image, factor, wraps,
                 circumference_mm, wavelength_mm, polarization, c_mm_s, t0_s, fs_hz, power, groups,
                 weight_sq):  # pragma: no cover - compiled by numba
    n = feature.shape[1]
    for r in range(rows.shape[0]):
        m = rows[r]
        for jj in range(angle_deg.shape[0]):
            diff = (angle_deg[jj] - rx_angles_deg[m] + 180.0) % 360.0 - 180.0
            if diff == -180.0:
                diff = 180.0
            arc = diff * circumference_mm / 360.0
            direction = circumference_mm if arc >= 0 else -circumference_mm
            for ii in range(axial_mm.shape[0]):
                z = axial_mm[ii]
                for f in range(offset.shape[0]):
                    incident = abs(offset[f] + sign[f] * z)
                    dz = image[f] - z
                    for wrap in range(wraps):
                        turns = (wrap + 1) // 2  # paths.wrap_turns: 0, -1, +1, -2, +2, ...
                        leg = arc + (-turns if wrap % 2 else turns) * direction
                        r_mm = math.sqrt(dz * dz + leg * leg)  # libm hypot is ~5x slower; mm: no overflow
                        w = factor[f] * math.sqrt(wavelength_mm / max(r_mm, 0.5 * wavelength_mm))
                        if polarization and r_mm > 0:
                            w *= abs(dz) / r_mm
                        k = math.floor(((incident + r_mm) / c_mm_s - t0_s) * fs_hz + 0.5)
                        if 0 <= k < n:
                            g = f * wraps + wrap
                            wp = w
                            for _ in range(power - 1):
                                wp *= w
                            groups[g, ii, jj] += wp * feature[m, k]
                            weight_sq[g, ii, jj] += wp * wp


def _compile_local():
    numba = numba_module()
    if numba is None:
        return None
    t = numba.types
    tail = (t.Array(t.int64, 1, "C", readonly=True), t.float64[::1], t.float64[::1], t.float64[::1], t.float64[::1],
            t.float64[::1], t.float64[::1], t.float64[::1], t.int64, t.float64, t.float64, t.boolean, t.float64,
            t.float64, t.float64, t.int64)
    signatures = [
        t.void(t.Array(t.complex128, 2, "C", readonly=True), *tail, t.complex128[:, :, ::1], t.float64[:, :, ::1]),
        t.void(t.Array(t.float64, 2, "C", readonly=True), *tail, t.float64[:, :, ::1], t.float64[:, :, ::1]),
    ]
    return njit(numba, signatures, _local_loops)


local_sums_compiled = _compile_local()


def coherent_energy_numpy(groups: np.ndarray, idx: np.ndarray, w: np.ndarray, correlation: np.ndarray,
                          n_groups: int, n_samples: int) -> np.ndarray:
    """[n_groups, n_pixels]: sum over pairs (a, b) of paths of one group of w_a w_b r(|k_a - k_b|) (module docstring).

    ``idx`` [P, n_pixels] sample of each path (``n_samples``: outside the record), ``w`` [P, n_pixels]."""
    out = np.zeros((n_groups, idx.shape[1]))
    span = correlation.size
    inside = idx < n_samples
    wv = np.where(inside, w.astype(np.float64), 0.0)
    for g in range(n_groups):
        members = np.flatnonzero(groups == g)
        for i, a in enumerate(members):
            out[g] += wv[a] * wv[a]
            for b in members[i + 1:]:
                lag = np.abs(idx[a].astype(np.int64) - idx[b])
                out[g] += 2.0 * wv[a] * wv[b] * np.where(lag < span, correlation[np.minimum(lag, span - 1)], 0.0)
    return out


def _coherent_energy_loops(starts, idx, w, correlation, n_samples, out):  # pragma: no cover - numba
    # Paths sorted by group: group g's are rows starts[g]:starts[g + 1].
    n_pix = idx.shape[1]
    span = correlation.shape[0]
    for g in range(starts.shape[0] - 1):
        for a in range(starts[g], starts[g + 1]):
            for x in range(n_pix):
                ka = idx[a, x]
                if ka >= n_samples:
                    continue
                wa = np.float64(w[a, x])
                out[g, x] += wa * wa
                for b in range(a + 1, starts[g + 1]):
                    kb = idx[b, x]
                    if kb >= n_samples:
                        continue
                    lag = ka - kb if ka > kb else kb - ka
                    if lag < span:
                        out[g, x] += 2.0 * wa * np.float64(w[b, x]) * correlation[lag]


def _compile_energy():
    numba = numba_module()
    if numba is None:
        return None
    t = numba.types
    signatures = [t.void(t.Array(t.int64, 1, "C", readonly=True), t.Array(t.int32, 2, "C", readonly=True),
                         t.Array(weight, 2, "C", readonly=True), t.Array(t.float64, 1, "C", readonly=True),
                         t.int64, t.float64[:, ::1]) for weight in (t.float32, t.float64)]
    return njit(numba, signatures, _coherent_energy_loops)


coherent_energy_compiled = _compile_energy()


def coherent_energy(groups: np.ndarray, idx: np.ndarray, w: np.ndarray, correlation: np.ndarray,
                    n_groups: int, n_samples: int) -> np.ndarray:
    """``coherent_energy_numpy``'s result, by the compiled kernel when available (dtypes: ``groups`` int64,
    ``idx`` int32, ``w`` float32 (a gather table's) or float64, ``correlation`` float64)."""
    if coherent_energy_compiled is None:
        return coherent_energy_numpy(groups, idx, w, correlation, n_groups, n_samples)
    out = np.zeros((n_groups, idx.shape[1]))
    order = np.argsort(groups, kind="stable")
    starts = np.searchsorted(groups[order], np.arange(n_groups + 1)).astype(np.int64)
    weights = w[order] if w.dtype in (np.float32, np.float64) else w[order].astype(np.float64)
    ro = [np.ascontiguousarray(a) for a in (starts, idx[order].astype(np.int32), weights,
                                            correlation.astype(np.float64))]
    for a in ro:
        a.setflags(write=False)
    coherent_energy_compiled(*ro, int(n_samples), out)
    return out


def cross_gram_numpy(groups: np.ndarray, idx: np.ndarray, w: np.ndarray, covariance: np.ndarray, n_groups: int,
                     n_samples: int) -> np.ndarray:
    """[n_groups, n_groups, n_pixels]: sum over pairs (a, b) of paths of w_a w_b C(k_b - k_a) into
    (group of a, group of b) (module docstring, 4); ``idx`` [P, n_pixels] (``n_samples``: outside the
    record), ``w`` [P, n_pixels], ``covariance`` C(d) for d = 0, 1, ... (C(-d) = conj C(d))."""
    span = covariance.size
    wv = np.where(idx < n_samples, w.astype(np.float64), 0.0)
    k = idx.astype(np.int64)
    lag = k[None, :, :] - k[:, None, :]  # [a, b, pixel]: k_b - k_a
    distance = np.abs(lag)
    value = np.where(distance < span, covariance[np.minimum(distance, span - 1)], 0.0)
    pairs = wv[:, None, :] * wv[None, :, :] * np.where(lag >= 0, value, np.conj(value))
    member = np.zeros((idx.shape[0], n_groups))
    member[np.arange(idx.shape[0]), groups] = 1.0
    return np.moveaxis(member.T @ np.moveaxis(pairs, 2, 0) @ member, 0, 2)


def _cross_gram_loops(groups, idx, w, covariance, n_samples, out):  # pragma: no cover - numba
    n_paths, n_pix = idx.shape
    span = covariance.shape[0]
    for a in range(n_paths):
        ga = groups[a]
        for b in range(n_paths):
            gb = groups[b]
            for x in range(n_pix):
                ka = idx[a, x]
                kb = idx[b, x]
                if ka >= n_samples or kb >= n_samples:
                    continue
                lag = kb - ka
                d = lag if lag >= 0 else -lag
                if d < span:
                    c = covariance[d] if lag >= 0 else np.conj(covariance[d])
                    out[ga, gb, x] += np.float64(w[a, x]) * np.float64(w[b, x]) * c


def _compile_cross_gram():
    numba = numba_module()
    return None if numba is None else njit(numba, None, _cross_gram_loops)


cross_gram_compiled = _compile_cross_gram()


def cross_gram(groups: np.ndarray, idx: np.ndarray, w: np.ndarray, covariance: np.ndarray, n_groups: int,
               n_samples: int) -> np.ndarray:
    """``cross_gram_numpy``'s result, by the compiled kernel when available."""
    if cross_gram_compiled is None:
        return cross_gram_numpy(groups, idx, w, covariance, n_groups, n_samples)
    out = np.zeros((n_groups, n_groups, idx.shape[1]), dtype=np.complex128)
    cross_gram_compiled(np.ascontiguousarray(groups, dtype=np.int64), np.ascontiguousarray(idx, dtype=np.int64),
                        np.ascontiguousarray(w, dtype=np.float64), np.ascontiguousarray(covariance, dtype=np.complex128),
                        int(n_samples), out)
    return out


PACK_CHUNK = 4096  # pixels packed at a time (bounds pack_lower's temporaries)
PIXEL_BLOCK = 512  # joint_power's pixels at a time (a block's sums and sums so far stay in cache)


def pack_lower(factors: np.ndarray, dtype: type = np.float32) -> np.ndarray:
    """Per-pixel lower-triangular factors W [..., G, G] (the whitening of a Gram M: W^H W = M^-1) -> the
    layout ``joint_power`` reads: [2, G (G + 1) / 2, n_pixels] of ``dtype``, the real and imaginary parts
    of each factor's lower triangle, row by row (numpy's ``tril_indices`` order). Single precision (the
    default, a map's full grid): a whitened sum |W b|^2 adds squares, nothing in it cancels, so W's
    rounding (~6e-8 of each term) moves the power by about cond(W) x 6e-8 of itself (cond(W) =
    sqrt(cond(M)) <= ~1.5e3 with the ridge), where the Hermitian form b^H M^-1 b read in single precision
    moves by up to cond(M) x 6e-8. Half the bytes of double, read once per pixel of every map."""
    n_groups = factors.shape[-1]
    flat = factors.reshape(-1, n_groups * n_groups)
    rows, cols = np.tril_indices(n_groups)
    lower = rows * n_groups + cols
    out: np.ndarray = np.empty((2, rows.size, flat.shape[0]), dtype=dtype)
    for start in range(0, flat.shape[0], PACK_CHUNK):
        part = flat[start:start + PACK_CHUNK][:, lower].T
        out[0, :, start:start + PACK_CHUNK] = part.real
        out[1, :, start:start + PACK_CHUNK] = part.imag
    return out


def joint_power_numpy(sums: np.ndarray, packed: np.ndarray) -> np.ndarray:
    """[n_pixels]: |W b|^2 = b^H M^-1 b per pixel, ``sums`` b [G, n_pixels], ``packed`` W as ``pack_lower``
    holds it."""
    b = sums.astype(np.complex128)
    power = np.zeros(b.shape[1:])
    first = 0
    for g in range(b.shape[0]):  # row g of the triangle: terms first .. first + g
        w = packed[0, first:first + g + 1].astype(np.float64) + 1j * packed[1, first:first + g + 1]
        whitened = np.sum(w * b[:g + 1], axis=0)
        power += whitened.real**2 + whitened.imag**2
        first += g + 1
    return power


def _joint_power_loops(sums, packed, out):  # pragma: no cover - numba
    n_groups, n_pix = sums.shape
    real, imag = packed[0], packed[1]
    br = np.empty((n_groups, PIXEL_BLOCK))  # a block's sums in double
    bi = np.empty((n_groups, PIXEL_BLOCK))
    acc_r = np.empty(PIXEL_BLOCK)
    acc_i = np.empty(PIXEL_BLOCK)
    for start in range(0, n_pix, PIXEL_BLOCK):
        n = min(PIXEL_BLOCK, n_pix - start)
        for g in range(n_groups):
            for x in range(n):
                br[g, x] = sums[g, start + x].real
                bi[g, x] = sums[g, start + x].imag
        for x in range(n):
            out[start + x] = 0.0
        k = 0
        for g in range(n_groups):
            acc_r[:n] = 0.0
            acc_i[:n] = 0.0
            for h in range(g + 1):
                wr = real[k, start:start + n]  # 1-D runs: the compiler vectorises the loop below
                wi = imag[k, start:start + n]  # (indexed 2-D, it stayed scalar: ~2x slower)
                b_r = br[h]
                b_i = bi[h]
                for x in range(n):
                    acc_r[x] += wr[x] * b_r[x] - wi[x] * b_i[x]
                    acc_i[x] += wr[x] * b_i[x] + wi[x] * b_r[x]
                k += 1
            for x in range(n):
                out[start + x] += acc_r[x] * acc_r[x] + acc_i[x] * acc_i[x]


def _compile_joint_power():
    numba = numba_module()
    return None if numba is None else njit(numba, None, _joint_power_loops)


joint_power_compiled = _compile_joint_power()


def joint_power(sums: np.ndarray, packed: np.ndarray) -> np.ndarray:
    """``joint_power_numpy``'s result (same pixel layout as ``sums[0]``), by the compiled kernel when available.

    ``sums`` [G, ...]; ``packed`` (``pack_lower``) for the pixels in ``sums[0]``'s C order. The
    kernel goes block by block of pixels, each triangle term a run along the block in real arithmetic
    (vectorised: ~2x faster than the whole complex matrix read pixel run by pixel run, and than the
    packed triangle read pixel by pixel; bench/bench_imaging.py, docs/benchmarks.md)."""
    shape = sums.shape[1:]
    flat_sums = np.ascontiguousarray(sums.reshape(sums.shape[0], -1))
    if joint_power_compiled is None:
        return joint_power_numpy(flat_sums, packed).reshape(shape)
    out = np.empty(flat_sums.shape[1])
    joint_power_compiled(flat_sums, packed, out)
    return out.reshape(shape)
