"""From what a node sends to what the imaging and the database take (pure)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from db.records import NodeGeometry
from gateway.config import GeometryOverride
from imaging.measurement import DEFAULT_VELOCITY_M_S, Measurement
from protocol.messages import InfoReply


@dataclass(frozen=True)
class NodeGeometryView:
    """The geometry the gateway images with: the node's INFO, overridden by the config."""

    geometry: NodeGeometry
    velocity_m_s: float
    wall_mm: float | None = None


def effective_geometry(info: InfoReply, override: GeometryOverride) -> NodeGeometryView:
    fields: dict[str, Any] = {
        "rx_angles_deg": list(info.rx_angles_deg),
        "tx_angles_deg": list(info.tx_angles_deg),
        "tx_rx_distance_mm": info.tx_rx_distance_mm,
        "circumference_mm": info.circumference_mm,
        "pipe_length_mm": None,
        "tx_axial_mm": None,
    }
    for key in fields:
        value = getattr(override, key)
        if value is not None:
            fields[key] = value
    velocity = override.velocity_m_s or info.velocity_m_s or DEFAULT_VELOCITY_M_S
    return NodeGeometryView(NodeGeometry(**fields), float(velocity), override.wall_mm)


def measurement_from_codes(
    codes: np.ndarray,
    volts_per_code: float,
    *,
    fs_hz: float,
    t0_s: float,
    view: NodeGeometryView,
    channels: tuple[int, ...] | None,
    excitation_hz: float,
    cycles: int,
    temperature_c: float | None,
) -> Measurement:
    """A Measurement in volts for the channels that were read (receiver angles picked to match)."""
    g = view.geometry
    rx = np.asarray(g.rx_angles_deg, dtype=np.float64)
    if channels is not None:
        rx = rx[list(channels)]
    return Measurement(
        traces=codes.astype(np.float32) * np.float32(volts_per_code),
        fs_hz=fs_hz,
        t0_s=t0_s,
        rx_angles_deg=rx,
        tx_angles_deg=np.asarray(g.tx_angles_deg, dtype=np.float64),
        tx_rx_distance_mm=g.tx_rx_distance_mm,
        circumference_mm=g.circumference_mm,
        velocity_m_s=view.velocity_m_s,
        excitation_hz=excitation_hz,
        cycles=cycles,
        temperature_c=float("nan") if temperature_c is None else temperature_c,
        pipe_length_mm=g.pipe_length_mm,
        tx_axial_mm=g.tx_axial_mm,
    )
