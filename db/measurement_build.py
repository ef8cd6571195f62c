"""From a node's ADC codes to the imaging's Measurement: a fresh transfer (the gateway) or a stored
record (the API's exports), built the same way (pure apart from reading a stored row).

A stored record is rebuilt with the velocity and wall thickness the gateway imaged it with
(revision 0004), so an exported file reproduces what the gateway saw; records stored before
that revision have none and get the T(0,1) default velocity.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session

from db.measurements import get_measurement, load_traces
from db.models import MeasurementRow
from db.records import NodeGeometry
from imaging.measurement import DEFAULT_VELOCITY_M_S, Measurement


@dataclass(frozen=True)
class NodeGeometryView:
    """The geometry a node's records are imaged with: rings and pipe, wave velocity, wall thickness."""

    geometry: NodeGeometry
    velocity_m_s: float
    wall_mm: float | None = None


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
        wall_mm=view.wall_mm,
    )


def stored_view(row: MeasurementRow) -> NodeGeometryView:
    """The geometry a stored record was imaged with: its node's rings, its own velocity and wall."""
    geometry = NodeGeometry.model_validate(row.node.geometry)
    velocity = row.velocity_m_s if row.velocity_m_s is not None else DEFAULT_VELOCITY_M_S
    return NodeGeometryView(geometry, velocity, row.wall_mm)


def stored_channels(row: MeasurementRow, geometry: NodeGeometry) -> tuple[int, ...] | None:
    """The receivers a record holds: all, or (fewer rows than receivers) the first ones, as the gateway reads them."""
    return None if row.n_channels == len(geometry.rx_angles_deg) else tuple(range(row.n_channels))


def stored_measurement(session: Session, measurement_id: int) -> Measurement:
    """A stored record in volts (codes x volts_per_code) as the gateway imaged it.

    Raises ``TracesPruned`` after retention, ``NotFound`` for an unknown id.
    """
    row = get_measurement(session, measurement_id)
    view = stored_view(row)
    return measurement_from_codes(
        load_traces(row),
        row.volts_per_code,
        fs_hz=row.fs_hz,
        t0_s=row.t0_s,
        view=view,
        channels=stored_channels(row, view.geometry),
        excitation_hz=row.excitation_hz,
        cycles=row.cycles,
        temperature_c=row.temperature_c,
    )
