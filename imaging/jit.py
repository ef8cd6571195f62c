"""numba for the project's compiled kernels: one switch for all of them.

numba is used when it is importable and ``PIPESENTRY_NUMBA`` is not "0"; every kernel keeps a
numpy fallback for when it is not. Compiled code goes to numba's on-disk cache, or stays in
memory where no cache location is writable.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from types import ModuleType
from typing import Any


def numba_module() -> ModuleType | None:
    """The numba module, or None when it is missing or switched off."""
    if os.environ.get("PIPESENTRY_NUMBA", "1") == "0":
        return None
    try:
        import numba
    except ImportError:
        return None
    return numba


def njit(numba: ModuleType, signatures: Any, function: Callable) -> Callable:
    """``function`` compiled with ``numba.njit`` (eagerly for ``signatures``, lazily when None), nogil,
    cached on disk when a cache location is writable."""
    decorate = numba.njit if signatures is None else lambda **kw: numba.njit(signatures, **kw)
    try:
        return decorate(cache=True, nogil=True)(function)
    except RuntimeError:  # no writable cache location: compile in memory instead
        return decorate(cache=False, nogil=True)(function)


__all__ = ["njit", "numba_module"]
