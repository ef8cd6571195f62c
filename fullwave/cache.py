"""The on-disk cache of simulations (the package's only I/O), and a case's pair from it.

A simulation is stored as ``<cache>/<key>.npz`` in the project's .npz format, its key a hash of
the spec (canonical JSON) and of the engine's code. The code version hashes the syntax trees of
the physics modules with their docstrings dropped, so a comment or docstring edit keeps the
cache while any change to the arithmetic invalidates it. Files are written to a temporary name
and renamed, so an interrupted or concurrent run never leaves a half-written record; an
unreadable cached file is recomputed and replaced.

Default location: ``$PIPESENTRY_FULLWAVE_CACHE``, else ``out/fullwave-cache`` under the project.
"""
from __future__ import annotations

import ast
import dataclasses
import hashlib
import json
import os
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from fullwave.acquisition import acquire_pair
from fullwave.cases import Case
from fullwave.record import SimulationSpec, simulate
from imaging.formats import MeasurementFileError, load_npz, npz_bytes
from imaging.measurement import Measurement

# The code a model's records depend on. Not compiled.py: it only picks numba or numpy for the same
# arithmetic (the tests hold the two equal), so a change of that plumbing keeps the cache.
COMMON_MODULES = ("absorber", "defects", "grid", "medium", "record", "sh", "transducers")
MODEL_MODULES = {"sh": (), "inplane": ("inplane",)}
PROJECT_ROOT = Path(__file__).resolve().parents[1]


class CacheError(OSError):
    """The cache directory cannot be created or written."""


def default_cache_dir() -> Path:
    return Path(os.environ.get("PIPESENTRY_FULLWAVE_CACHE", PROJECT_ROOT / "out" / "fullwave-cache"))


def _without_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]  # type: ignore[attr-defined]
    return tree


@lru_cache(maxsize=4)
def code_version(model: str = "sh") -> str:
    """Hash of the code a model's records depend on (docstrings and comments excluded)."""
    digest = hashlib.sha256()
    here = Path(__file__).parent
    for name in COMMON_MODULES + MODEL_MODULES.get(model, ()):
        digest.update(name.encode())
        digest.update(ast.dump(_without_docstrings(ast.parse((here / f"{name}.py").read_text()))).encode())
    return digest.hexdigest()[:16]


def spec_key(spec: SimulationSpec) -> str:
    text = json.dumps(dataclasses.asdict(spec), sort_keys=True, default=str)
    return hashlib.sha256(f"{code_version(spec.model)}:{text}".encode()).hexdigest()[:24]


def cached_simulation(spec: SimulationSpec, cache_dir: Path | None = None) -> Measurement:
    """The noise-free record of ``spec``, from the cache or simulated (and then stored)."""
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = directory / f"{spec_key(spec)}.npz"
    if path.exists():
        try:
            return load_npz(path)
        except MeasurementFileError:
            pass  # a damaged cache entry: simulate again and replace it below
    record = simulate(spec)
    _write_atomically(path, npz_bytes(record))
    return record


def _write_atomically(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        raise CacheError(f"cannot write the full-wave cache {path.parent}: {exc.strerror or exc}") from exc


def case_pair(case: Case, cache_dir: Path | None = None) -> tuple[Measurement, Measurement]:
    """(baseline, current) of ``case`` as the node would deliver them (noise, ADC, decimation applied)."""
    baseline = cached_simulation(case.baseline, cache_dir)
    current = cached_simulation(case.current, cache_dir)
    return acquire_pair(baseline, current, np.random.default_rng(case.seed), noisy=case.noisy,
                        decimation=case.decimation)


__all__ = ["CacheError", "cached_simulation", "case_pair", "code_version", "default_cache_dir", "spec_key"]
