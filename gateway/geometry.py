"""The geometry the gateway images a node with: what the node reports in INFO, overridden by the config."""
from __future__ import annotations

from db.measurement_build import NodeGeometryView
from db.records import NodeGeometry
from gateway.config import GeometryOverride
from imaging.measurement import DEFAULT_VELOCITY_M_S
from protocol.messages import InfoReply


def effective_geometry(info: InfoReply, override: GeometryOverride) -> NodeGeometryView:
    fields: dict[str, list[float] | float | None] = {
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
    return NodeGeometryView(NodeGeometry.model_validate(fields), float(velocity), override.wall_mm)
