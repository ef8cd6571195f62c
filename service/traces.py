"""Raw traces of a stored measurement as JSON, as the .npz interchange file and as CSV (docs/formats.md)."""
from __future__ import annotations

import numpy as np
from sqlalchemy.orm import Session

from db.measurement_build import stored_channels, stored_measurement
from db.measurements import get_measurement, load_traces
from db.records import NodeGeometry
from imaging.formats import csv_text, npz_bytes
from service import schemas


def traces_json(session: Session, measurement_id: int, units: schemas.TraceUnits) -> schemas.Traces:
    row = get_measurement(session, measurement_id)
    codes = load_traces(row)
    geometry = NodeGeometry.model_validate(row.node.geometry)
    channels = stored_channels(row, geometry)
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
    """The record as the gateway imaged it (its velocity and wall), as .npz file contents."""
    return npz_bytes(stored_measurement(session, measurement_id))


def traces_csv(session: Session, measurement_id: int) -> str:
    return csv_text(stored_measurement(session, measurement_id))
