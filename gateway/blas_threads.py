"""One BLAS thread per node worker: each worker's imaging runs on its own thread, on one core.

A node worker runs ``assess()`` on its own thread, sized for one core (docs/benchmarks.md). numpy's
OpenBLAS otherwise starts a thread per core, and every worker's linear algebra (a sparse ring's echo
fits: pseudo-inverses, batched products) spreads over all of them: two workers side by side then spin
against each other. Measured on a 2-core VM (2026-12-07, two threads assessing full-wave dev records,
8- and 16-ring, side by side as two node workers do; two rounds): 24.7 / 25.2 s wall and 48.7 / 49.7 s
of CPU with OpenBLAS's own threads, 11.8 / 11.8 s and 18.8 / 18.4 s with one.

OpenBLAS reads the variables when it loads, so they are set before numpy is first imported: the gateway
command calls ``one_blas_thread`` before it imports the daemon. An operator's own value is kept (a
gateway with few nodes and many cores may give its workers more).
"""
from __future__ import annotations

from collections.abc import MutableMapping

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str]) -> tuple[str, ...]:
    """Set each of BLAS_THREAD_VARIABLES that ``environ`` lacks (or holds empty) to "1"; the names it set."""
    missing = tuple(name for name in BLAS_THREAD_VARIABLES if not environ.get(name, "").strip())
    for name in missing:
        environ[name] = "1"
    return missing
