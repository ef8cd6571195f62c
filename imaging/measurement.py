"""One acquisition from all receivers of a node, with the geometry needed to image it.

This is the in-memory form of the interchange format described in docs/formats.md.
"""
from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")

DEFAULT_VELOCITY_M_S = 3130.0  # T(0,1) group velocity in steel (paper, section 2)


class MeasurementError(ValueError):
    """A measurement is malformed: missing fields, bad shapes, non-finite samples."""


@dataclass(frozen=True)
class Measurement:
    """Traces [n_rx, n_samples] sampled at ``fs_hz``; sample 0 is at ``t0_s`` after excitation start.

    Angles are in degrees on the pipe circumference, distances in millimetres.
    ``tx_axial_mm`` is the Tx ring's axial position from the pipe end behind it; the Rx ring
    sits ``tx_rx_distance_mm`` further along. Both pipe fields are optional (None when unknown),
    as is ``wall_mm``, the wall thickness (for the mid-wall circumference waves travel).
    """

    traces: np.ndarray
    fs_hz: float
    t0_s: float
    rx_angles_deg: np.ndarray
    tx_angles_deg: np.ndarray
    tx_rx_distance_mm: float
    circumference_mm: float
    velocity_m_s: float = DEFAULT_VELOCITY_M_S
    excitation_hz: float = 85e3
    cycles: int = 5
    temperature_c: float = math.nan
    pipe_length_mm: float | None = None
    tx_axial_mm: float | None = None
    wall_mm: float | None = None
    extra: dict = field(default_factory=dict, compare=False)
    # What has been derived from this record (``derived``): kept with the record, not in a module.
    _derived: dict[str, tuple[Hashable, Any]] = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        traces = np.asarray(self.traces)
        if traces.ndim != 2:
            raise MeasurementError(f"traces must be 2-D [n_rx, n_samples], got shape {traces.shape}")
        if traces.shape[0] < 1 or traces.shape[1] < 2:
            raise MeasurementError(f"traces has no data: shape {traces.shape}")
        if not np.all(np.isfinite(traces)):
            bad = int(np.count_nonzero(~np.isfinite(traces)))
            raise MeasurementError(f"traces contain {bad} NaN/inf samples")
        object.__setattr__(self, "traces", traces.astype(np.float32, copy=False))
        rx = np.atleast_1d(np.asarray(self.rx_angles_deg, dtype=np.float64))
        tx = np.atleast_1d(np.asarray(self.tx_angles_deg, dtype=np.float64))
        if rx.ndim != 1 or rx.shape[0] != traces.shape[0]:
            raise MeasurementError(
                f"rx_angles_deg has {rx.size} entries but traces has {traces.shape[0]} receivers"
            )
        if tx.ndim != 1 or tx.size < 1:
            raise MeasurementError("tx_angles_deg must list at least one transmitter angle")
        if not (np.all(np.isfinite(rx)) and np.all(np.isfinite(tx))):
            raise MeasurementError("ring angles must be finite")
        object.__setattr__(self, "rx_angles_deg", rx)
        object.__setattr__(self, "tx_angles_deg", tx)
        for name in ("fs_hz", "tx_rx_distance_mm", "circumference_mm", "velocity_m_s", "excitation_hz"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise MeasurementError(f"{name} must be a positive finite number, got {value!r}")
            object.__setattr__(self, name, value)
        t0 = float(self.t0_s)
        if not math.isfinite(t0):
            raise MeasurementError(f"t0_s must be finite, got {t0!r}")
        object.__setattr__(self, "t0_s", t0)
        cycles = int(self.cycles)
        if cycles < 1 or cycles != self.cycles:
            raise MeasurementError(f"cycles must be a positive integer, got {self.cycles!r}")
        object.__setattr__(self, "cycles", cycles)
        object.__setattr__(self, "temperature_c", float(self.temperature_c))
        for name in ("pipe_length_mm", "tx_axial_mm"):
            value = getattr(self, name)
            if value is None:
                continue
            value = float(value)
            if math.isnan(value):
                object.__setattr__(self, name, None)
                continue
            if not (math.isfinite(value) and value >= 0):
                raise MeasurementError(f"{name} must be a non-negative finite number, got {value!r}")
            object.__setattr__(self, name, value)
        if self.wall_mm is not None:
            wall = float(self.wall_mm)
            if not (math.isnan(wall) or (math.isfinite(wall) and wall > 0)):
                raise MeasurementError(f"wall_mm must be a positive finite number, got {self.wall_mm!r}")
            object.__setattr__(self, "wall_mm", None if math.isnan(wall) else wall)
        if (
            self.pipe_length_mm is not None
            and self.tx_axial_mm is not None
            and self.tx_axial_mm + self.tx_rx_distance_mm > self.pipe_length_mm
        ):
            raise MeasurementError("the Rx ring (tx_axial_mm + tx_rx_distance_mm) lies beyond pipe_length_mm")

    def traces_digest(self) -> tuple[bytes, tuple[int, ...], str]:
        """(SHA-1 of the traces' bytes, their shape, their dtype): what a ``derived`` key names the
        traces by, so that traces changed in place are derived again."""
        traces = np.ascontiguousarray(self.traces)
        return (hashlib.sha1(traces.view(np.uint8).data, usedforsecurity=False).digest(), traces.shape,
                traces.dtype.str)

    def derived(self, name: str, key: Hashable, compute: Callable[[], T]) -> T:
        """``compute()``, remembered with this record under ``name`` while ``key`` stays the same.

        The memo belongs to the record, so there is no cache shared between records or threads:
        a node's baseline library keeps what was derived from its baselines for as long as it
        keeps them, and drops it with them. ``key`` names what the value depends on (e.g. a
        digest of the traces, which a caller could change in place); a different key computes
        again. Two threads asking at once may both compute; each stores a whole, equal value.
        """
        entry = self._derived.get(name)
        if entry is not None and entry[0] == key:
            return entry[1]
        value = compute()
        self._derived[name] = (key, value)
        return value

    @property
    def n_rx(self) -> int:
        return int(self.traces.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.traces.shape[1])

    @property
    def outer_diameter_mm(self) -> float:
        return self.circumference_mm / math.pi
