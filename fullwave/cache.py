"""The on-disk cache of simulations (the package's only I/O), and a case's pair from it.

A simulation is stored as ``<cache>/<key>.npz`` in the project's .npz format, its key a hash of
the spec (canonical JSON) and of the engine's *behaviour*: the code version of a model is the
hash of the exact output of two tiny reference runs of it (every feature on: notch, mass,
tilted patches, temperature, free and absorbing ends), computed once per process in a few
milliseconds. A refactor that keeps the arithmetic (the same operations in the same order) keeps
the cache; any change to the numbers, down to the last bit, renews it (so may another numba or
CPU: a cache is per machine). Files
are written to a temporary name and renamed, so an interrupted or concurrent run never leaves a
half-written record; an unreadable cached file is recomputed and replaced.

Default location: ``$PIPESENTRY_FULLWAVE_CACHE``, else ``out/fullwave-cache`` under the project.
"""
from __future__ import annotations

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
from fullwave.defects import Mass, Notch
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.formats import MeasurementFileError, load_npz, npz_bytes
from imaging.measurement import Measurement

PROJECT_ROOT = Path(__file__).resolve().parents[1]


class CacheError(OSError):
    """The cache directory cannot be created or written."""


def default_cache_dir() -> Path:
    return Path(os.environ.get("PIPESENTRY_FULLWAVE_CACHE", PROJECT_ROOT / "out" / "fullwave-cache"))


def _reference_specs(model: str) -> list[SimulationSpec]:
    """Two tiny runs that go through every part of a record: grid, medium, both defect kinds,
    temperature, tilted patches, both end conditions, the kernel, resampling and gain."""
    spec = SimulationSpec(
        pipe=PipeModel(length_mm=80.0, circumference_mm=40.0, absorber_mm=10.0),
        rings=RingLayout(tx_axial_mm=15.0, tx_rx_distance_mm=50.0, n_transducers=2, patch_circumferential_mm=10.0,
                         patch_axial_mm=10.0, tilt_deg=10.0),
        defects=(Notch(axial_mm=20.0, angle_deg=90.0, circumferential_mm=8.0, axial_length_mm=6.0, depth_mm=1.0),
                 Mass(axial_mm=35.0, angle_deg=270.0, diameter_mm=6.0, mass_kg=0.5)),
        temperature_c=27.0, cell_mm=2.0, n_samples=400, model=model)  # type: ignore[arg-type]
    return [spec, spec.with_changes(pipe=dataclasses.replace(spec.pipe, ends="absorbing"))]


@lru_cache(maxsize=4)
def code_version(model: str = "sh") -> str:
    """Hash of what the engine computes for ``model`` (its reference runs' exact samples)."""
    digest = hashlib.sha256(model.encode())
    for spec in _reference_specs(model):
        digest.update(np.ascontiguousarray(simulate(spec).traces).tobytes())
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
