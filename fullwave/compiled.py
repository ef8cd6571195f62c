"""numba for the time-stepping loops, when it is installed and PIPESENTRY_NUMBA is not "0" (imaging/jit.py).

Kernels are compiled lazily on first use and kept in numba's on-disk cache; without numba the
kernels fall back to their numpy reference (same arithmetic, vectorised per time step, slower).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from imaging.jit import njit, numba_module


def jit(function: Callable) -> Callable | None:
    """``function`` compiled by numba (lazily, cached on disk), or None without numba."""
    numba = numba_module()
    return None if numba is None else njit(numba, None, function)


def kernel_array(values: np.ndarray, dtype: type) -> np.ndarray:
    """A C-contiguous copy (or view) in the kernels' dtype."""
    return np.ascontiguousarray(values, dtype=dtype)


__all__ = ["jit", "kernel_array"]
