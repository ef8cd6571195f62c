"""Raw traces of a stored measurement as JSON, as the .npz interchange file and as CSV (docs/formats.md)."""
from __future__ import annotations

import numpy as np
from sqlalchemy.orm import Session

from db.measurements import get_measurement, load_traces
from db.models import MeasurementRow
from db.records import NodeGeometry
from gateway.measurement_build import NodeGeometryView, measurement_from_codes
from imaging.formats import csv_text, npz_bytes
from imaging.measurement import DEFAULT_VELOCITY_M_S, Measurement
from service import schemas


def _rx_channels(row: MeasurementRow, geometry: NodeGeometry) -> tuple[int, ...] | None:
    # As the gateway does: a record with fewer rows than receivers holds the first channels.
    return None if row.n_channels == len(geometry.rx_angles_deg) else tuple(range(row.n_channels))


def stored_measurement(session: Session, measurement_id: int) -> Measurement:
    """The measurement in volts (codes x volts_per_code) with its node's geometry.

    The node's velocity is not stored, so the T(0,1) default (3130 m/s in steel) is used.
    Raises ``TracesPruned`` after retention, ``NotFound`` for an unknown id.
    """
    row = get_measurement(session, measurement_id)
    codes = load_traces(row)
    geometry = NodeGeometry.model_validate(row.node.geometry)
    return measurement_from_codes(
        codes,
        row.volts_per_code,
        fs_hz=row.fs_hz,
        t0_s=row.t0_s,
        view=NodeGeometryView(geometry, DEFAULT_VELOCITY_M_S),
        channels=_rx_channels(row, geometry),
        excitation_hz=row.excitation_hz,
        cycles=row.cycles,
        temperature_c=row.temperature_c,
    )


def traces_json(session: Session, measurement_id: int, units: schemas.TraceUnits) -> schemas.Traces:
    row = get_measurement(session, measurement_id)
    codes = load_traces(row)
    geometry = NodeGeometry.model_validate(row.node.geometry)
    channels = _rx_channels(row, geometry)
    rx = np.asarray(geometry.rx_angles_deg, dtype=np.float64)
    if channels is not None:
        rx = rx[list(channels)]
    values = codes if units == schemas.TraceUnits.CODES else codes.astype(np.float32) * np.float32(row.volts_per_code)
    return schemas.Traces(
        measurement_id=row.id,
        units=units,
        fs_hz=row.fs_hz,
        t0_s=row.t0_s,
        volts_per_code=row.volts_per_code,
        rx_angles_deg=rx.tolist(),
        traces=values.tolist(),
    )


def traces_npz(session: Session, measurement_id: int) -> bytes:
    return npz_bytes(stored_measurement(session, measurement_id))


def traces_csv(session: Session, measurement_id: int) -> str:
    return csv_text(stored_measurement(session, measurement_id))
