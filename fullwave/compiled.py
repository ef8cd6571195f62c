"""numba for the time-stepping loops, when it is installed and PIPESENTRY_NUMBA is not "0".

Kernels are compiled lazily on first use and kept in numba's on-disk cache; without numba the
kernels fall back to their numpy reference (same arithmetic, vectorised per time step, slower).
"""
from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np


def numba_module():
    """The numba module, or None when it is missing or switched off."""
    if os.environ.get("PIPESENTRY_NUMBA", "1") == "0":
        return None
    try:
        import numba
    except ImportError:
        return None
    return numba


def jit(function: Callable) -> Callable | None:
    """``function`` compiled by numba (lazily, cached on disk), or None without numba."""
    numba = numba_module()
    if numba is None:
        return None
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # no writable cache location
        return numba.njit(cache=False, nogil=True)(function)


def kernel_array(values: np.ndarray, dtype: type) -> np.ndarray:
    """A C-contiguous copy (or view) in the kernels' dtype."""
    return np.ascontiguousarray(values, dtype=dtype)


__all__ = ["jit", "kernel_array", "numba_module"]
