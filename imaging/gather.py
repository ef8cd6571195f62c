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
            other = arc - circumference_mm if arc >= 0 else arc + circumference_mm
            for ii in range(axial_mm.shape[0]):
                z = axial_mm[ii]
                for f in range(offset.shape[0]):
                    incident = abs(offset[f] + sign[f] * z)
                    dz = image[f] - z
                    for wrap in range(wraps):
                        leg = arc if wrap == 0 else other
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
