"""Inner loops of the echo fit (imaging/echofit.py), compiled with numba when it is installed.

A fit's columns are shifted, possibly record-cut copies of two shapes (the burst and its quadrature
twin): column ``a`` on receiver ``m`` is ``shapes[kind[m, a]]`` starting at sample ``starts[m, a]``,
used where ``valid[m, a]`` (a valid column overlaps the record: -size < start < n). Two sums are needed:

1. the normal equations: per receiver, the Gram matrix of the columns (each entry a difference
   of two entries of the shapes' partial-product table, however the record cuts the pair) and
   the right-hand side (each column's samples times the residual's);
2. the synthesis: each column's shape times its coefficient, added at its samples into its
   owner's (the position's) echoes.

A model with Tx elements (imaging/echofit.py ``group_waves``) needs a third: its columns themselves,
each a coherence group's paths added together (a weighted, carrier-shifted copy of the burst pair at
each path's arrival sample). The numpy form convolves impulse trains with the two shapes by FFT;
the compiled one adds each path's copy where it falls (8 receivers x 54 groups of a 75 kHz 8-ring:
one FFT pass ~60-80 ms, the loop a few ms).

Each has two implementations of the same sum: a compiled numba kernel (one pass over the
columns' own samples, no temporaries) and a vectorised numpy form (gathers and a bincount over
[receivers x columns x burst length] arrays), used when numba is missing or switched off
(``PIPESENTRY_NUMBA=0``, imaging/jit.py). Tests hold them equal.
"""
from __future__ import annotations

import numpy as np
from scipy import fft as sp_fft

from imaging.jit import njit, numba_module


def normal_equations_numpy(residual: np.ndarray, starts: np.ndarray, kind: np.ndarray, valid: np.ndarray,
                           shapes: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(gram [m, a, a], rhs [m, a]) of the columns; ``table`` as imaging/echofit.py ``_partial_products``."""
    n_rx, n = residual.shape
    size = shapes.shape[1]
    starts = np.where(valid, starts, 0)
    ka, kb = starts[:, :, None], starts[:, None, :]
    lo = np.maximum(np.maximum(ka, kb), 0)
    hi = np.minimum(np.minimum(ka, kb) + size, n)
    lag = np.clip(kb - ka, 1 - size, size - 1) + size - 1
    xa, xb = kind[:, :, None], kind[:, None, :]
    u1, u0 = np.clip(hi - ka, 0, size), np.clip(lo - ka, 0, size)
    gram = np.where((hi > lo) & valid[:, :, None] & valid[:, None, :],
                    table[xa, xb, lag, u1] - table[xa, xb, lag, u0], 0.0)
    padded = np.zeros((n_rx, n + 2 * size))
    padded[:, size:size + n] = residual
    window = _windows(starts, size)
    segments = np.take_along_axis(padded, window.reshape(n_rx, -1), axis=1).reshape(window.shape)
    rhs = np.where(valid, np.einsum("mau,mau->ma", segments, shapes[kind]), 0.0)
    return gram, rhs


def synthesise_numpy(coef: np.ndarray, starts: np.ndarray, kind: np.ndarray, valid: np.ndarray, owner: np.ndarray,
                     shapes: np.ndarray, n_pos: int, n: int) -> np.ndarray:
    """[n_pos, m, n]: each owner's echoes, the columns' shapes times ``coef`` [m, a] added at their samples."""
    n_rx = coef.shape[0]
    size = shapes.shape[1]
    starts = np.where(valid, starts, 0)
    width = n + 2 * size
    flat = (owner[:, :, None] * n_rx + np.arange(n_rx)[:, None, None]) * width + _windows(starts, size)
    weights = np.where(valid, coef, 0.0)[:, :, None] * shapes[kind]
    total = np.bincount(flat.ravel(), weights=weights.ravel(), minlength=n_pos * n_rx * width)
    return total.reshape(n_pos, n_rx, width)[:, :, size:size + n]


def group_columns_numpy(rx: np.ndarray, pos: np.ndarray, group: np.ndarray, starts: np.ndarray, c: np.ndarray,
                        s: np.ndarray | None, shapes: np.ndarray, out_shape: tuple[int, int, int, int]) -> np.ndarray:
    """[m, pos, group, 2, n]: every path (receiver ``rx``, position ``pos``, coherence group ``group``, first
    sample ``starts``) adds ``c`` x burst - ``s`` x quadrature to its group's burst column and ``c`` x quadrature
    + ``s`` x burst to its quadrature column (``s`` None: no carrier shift), cut to the record's n samples.
    Impulse trains convolved with the two shapes, one FFT each."""
    n_rx, n_pos, n_groups, n = out_shape
    size = shapes.shape[1]
    width = n + size
    impulses = np.zeros((n_rx, n_pos, n_groups, 1 if s is None else 2, width))
    at = (rx, pos, group, starts + size)
    np.add.at(impulses[..., 0, :], at, c)
    if s is not None:
        np.add.at(impulses[..., 1, :], at, s)
    n_fft = sp_fft.next_fast_len(width + size, real=True)
    burst, quadrature = sp_fft.rfft(shapes, n_fft, axis=-1)
    spec = sp_fft.rfft(impulses, n_fft, axis=-1)
    if s is not None:  # sin(x - phi) = sin x cos phi - cos x sin phi; cos(x - phi) = cos x cos phi + sin x sin phi
        spec = np.stack([spec[..., 0, :] * burst - spec[..., 1, :] * quadrature,
                         spec[..., 0, :] * quadrature + spec[..., 1, :] * burst], axis=-2)
    else:
        spec = spec * np.stack([burst, quadrature])
    return sp_fft.irfft(spec, n_fft, axis=-1)[..., size:size + n]


def _windows(starts: np.ndarray, size: int) -> np.ndarray:
    """Each column's sample indices [m, a, size] into a record zero-padded by ``size`` either side."""
    return (size + starts)[:, :, None] + np.arange(size)


def _normal_loops(residual, starts, kind, valid, shapes, table, gram, rhs):  # pragma: no cover - compiled by numba
    n_rx, n = residual.shape
    n_cols = starts.shape[1]
    size = shapes.shape[1]
    for m in range(n_rx):
        for a in range(n_cols):
            if not valid[m, a]:
                continue
            ka = starts[m, a]
            xa = kind[m, a]
            total = 0.0
            for t in range(max(ka, 0), min(ka + size, n)):
                total += residual[m, t] * shapes[xa, t - ka]
            rhs[m, a] = total
            for b in range(n_cols):
                if not valid[m, b]:
                    continue
                kb = starts[m, b]
                lo = max(ka, kb, 0)
                hi = min(min(ka, kb) + size, n)
                if hi <= lo:
                    continue
                lag = min(max(kb - ka, 1 - size), size - 1) + size - 1
                u1 = min(max(hi - ka, 0), size)
                u0 = min(max(lo - ka, 0), size)
                gram[m, a, b] = table[xa, kind[m, b], lag, u1] - table[xa, kind[m, b], lag, u0]


def _synthesis_loops(coef, starts, kind, valid, owner, shapes, out):  # pragma: no cover - compiled by numba
    n_rx, n_cols = coef.shape
    n = out.shape[2]
    size = shapes.shape[1]
    for m in range(n_rx):
        for a in range(n_cols):
            if not valid[m, a]:
                continue
            ka = starts[m, a]
            c = coef[m, a]
            xa = kind[m, a]
            p = owner[m, a]
            for t in range(max(ka, 0), min(ka + size, n)):
                out[p, m, t] += c * shapes[xa, t - ka]


def _group_loops(rx, pos, group, starts, c, s, shapes, out):  # pragma: no cover - compiled by numba
    n = out.shape[4]
    size = shapes.shape[1]
    for i in range(starts.size):
        k = starts[i]
        m, p, g, ci, si = rx[i], pos[i], group[i], c[i], s[i]
        for t in range(max(k, 0), min(k + size, n)):
            b = shapes[0, t - k]
            q = shapes[1, t - k]
            out[m, p, g, 0, t] += ci * b - si * q
            out[m, p, g, 1, t] += ci * q + si * b


def _compile():
    numba = numba_module()
    if numba is None:
        return None, None, None
    return njit(numba, None, _normal_loops), njit(numba, None, _synthesis_loops), njit(numba, None, _group_loops)


normal_compiled, synthesis_compiled, group_compiled = _compile()


def normal_equations(residual: np.ndarray, starts: np.ndarray, kind: np.ndarray, valid: np.ndarray,
                     shapes: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``normal_equations_numpy``'s sums, by the compiled kernel when available."""
    if normal_compiled is None:
        return normal_equations_numpy(residual, starts, kind, valid, shapes, table)
    n_rx, n_cols = starts.shape
    gram, rhs = np.zeros((n_rx, n_cols, n_cols)), np.zeros((n_rx, n_cols))
    normal_compiled(*_contiguous(residual, starts, kind, valid), np.ascontiguousarray(shapes, dtype=np.float64),
                    table, gram, rhs)
    return gram, rhs


def synthesise(coef: np.ndarray, starts: np.ndarray, kind: np.ndarray, valid: np.ndarray, owner: np.ndarray,
               shapes: np.ndarray, n_pos: int, n: int) -> np.ndarray:
    """``synthesise_numpy``'s sums, by the compiled kernel when available."""
    if synthesis_compiled is None:
        return synthesise_numpy(coef, starts, kind, valid, owner, shapes, n_pos, n)
    out = np.zeros((n_pos, coef.shape[0], n))
    synthesis_compiled(*_contiguous(coef, starts, kind, valid), np.ascontiguousarray(owner, dtype=np.int64),
                       np.ascontiguousarray(shapes, dtype=np.float64), out)
    return out


def group_columns(rx: np.ndarray, pos: np.ndarray, group: np.ndarray, starts: np.ndarray, c: np.ndarray,
                  s: np.ndarray | None, shapes: np.ndarray, out_shape: tuple[int, int, int, int]) -> np.ndarray:
    """``group_columns_numpy``'s columns, by the compiled kernel when available."""
    if group_compiled is None:
        return group_columns_numpy(rx, pos, group, starts, c, s, shapes, out_shape)
    n_rx, n_pos, n_groups, n = out_shape
    out = np.zeros((n_rx, n_pos, n_groups, 2, n))
    index = [np.ascontiguousarray(x, dtype=np.int64) for x in (rx, pos, group, starts)]
    c = np.ascontiguousarray(c, dtype=np.float64)
    group_compiled(*index, c, np.zeros_like(c) if s is None else np.ascontiguousarray(s, dtype=np.float64),
                   np.ascontiguousarray(shapes, dtype=np.float64), out)
    return out


def _contiguous(values: np.ndarray, starts: np.ndarray, kind: np.ndarray,
                valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (np.ascontiguousarray(values, dtype=np.float64), np.ascontiguousarray(starts, dtype=np.int64),
            np.ascontiguousarray(kind, dtype=np.int64), np.ascontiguousarray(valid, dtype=np.bool_))


__all__ = ["group_columns", "group_columns_numpy", "normal_equations", "normal_equations_numpy", "synthesise",
           "synthesise_numpy"]
