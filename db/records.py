"""What the gateway hands to storage: validated inputs of the repository functions."""
from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt

from db.models import MapSource, MeasurementKind, NodeState, Severity


class NodeGeometry(BaseModel):
    """Ring layout of a node (stored as JSON in ``nodes.geometry``). Angles in degrees."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rx_angles_deg: list[float] = Field(min_length=1)
    tx_angles_deg: list[float] = Field(min_length=1)
    tx_rx_distance_mm: PositiveFloat
    circumference_mm: PositiveFloat
    pipe_length_mm: PositiveFloat | None = None
    tx_axial_mm: float | None = Field(None, ge=0)


class MapGrid(BaseModel):
    """Pixel grid of a DI map (stored as JSON in ``di_maps.grid``); pixels are [axial, angle]."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    axial_start_mm: float
    axial_step_mm: PositiveFloat
    axial_count: PositiveInt
    angle_start_deg: float
    angle_step_deg: PositiveFloat
    angle_count: PositiveInt

    @property
    def shape(self) -> tuple[int, int]:
        return (self.axial_count, self.angle_count)


@dataclass(frozen=True)
class NodeInfo:
    """A node's identity and configuration, from its INFO reply."""

    node_id: str
    port_url: str
    firmware: str
    protocol_version: int
    n_channels: int
    fs_hz: float
    geometry: NodeGeometry


@dataclass(frozen=True)
class DiMapInput:
    """A DI map to store with its measurement; ``pixels`` is float32 [axial_count, angle_count]."""

    source: MapSource
    method: str
    grid: MapGrid
    pixels: np.ndarray
    baseline_measurement_id: int | None

    def __post_init__(self) -> None:
        pixels = np.asarray(self.pixels)
        if pixels.dtype != np.float32:
            raise ValueError(f"DI map pixels must be float32, got {pixels.dtype}")
        if pixels.shape != self.grid.shape:
            raise ValueError(f"DI map pixels have shape {pixels.shape}, the grid says {self.grid.shape}")
        if not np.any(np.isfinite(pixels)):
            raise ValueError("DI map has no finite pixel")

    @property
    def peak_di(self) -> float:
        return float(np.nanmax(np.where(np.isfinite(self.pixels), self.pixels, np.nan)))


@dataclass(frozen=True)
class DetectionInput:
    """The verdict on a monitor measurement; the location is None when nothing stands out."""

    peak_di: float | None  # None when the imaging abstained (no valid baseline)
    threshold: float | None  # None while the node's threshold is being calibrated
    state: NodeState
    axial_mm: float | None = None
    angle_deg: float | None = None
    confidence: float | None = None
    method: str | None = None
    defects: list[dict[str, Any]] | None = None
    sensor_faults: list[dict[str, Any]] | None = None
    baseline_measurement_id: int | None = None
    stretch: float | None = None
    abstain_reason: str | None = None  # why the imaging abstained (peak_di None)


@dataclass(frozen=True)
class StateChangeInput:
    """A node state transition caused by the measurement it is stored with."""

    from_state: NodeState
    to_state: NodeState

    def __post_init__(self) -> None:
        if self.from_state == self.to_state:
            raise ValueError(f"a state change must change the state (both are {self.from_state.value})")


@dataclass(frozen=True)
class EventInput:
    """An alert for the outbox; one pending delivery is created per named sink."""

    kind: str
    severity: Severity
    payload: dict[str, Any]
    sinks: tuple[str, ...] = ()
    id: uuid.UUID = field(default_factory=uuid.uuid4)


@dataclass(frozen=True)
class AcquisitionInput:
    """One acquisition as the node sent it: raw ADC codes int16 [n_channels, n_samples] and how they were
    taken, as the node states it (not what the gateway asked for)."""

    acquired_at: datetime
    node_measurement_id: int
    codes: np.ndarray
    volts_per_code: float
    fs_hz: float
    t0_s: float
    averaging: int
    excitation_hz: float
    cycles: int
    temperature_c: float | None = None
    velocity_m_s: float | None = None  # the wave velocity the record is imaged with
    wall_mm: float | None = None  # the wall thickness it is imaged with
    boot_id: int | None = None  # the node's boot it was taken in


@dataclass(frozen=True)
class CycleRecord:
    """Everything one gateway cycle stores, in one transaction (``db.cycles.store_cycle``)."""

    acquisition: AcquisitionInput
    kind: MeasurementKind
    error_counters: Mapping[str, int]  # the node's and the gateway's counters after this cycle
    di_maps: Sequence[DiMapInput] = ()
    detection: DetectionInput | None = None
    state_change: StateChangeInput | None = None
    activate_baseline: str | None = None  # the reason, when the record becomes the node's active baseline
