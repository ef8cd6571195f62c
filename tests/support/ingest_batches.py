"""Builders of uplink batches as a gateway would send them (uplink/contract.py), for the centre's tests."""
from __future__ import annotations

import hashlib
import uuid
from datetime import datetime, timedelta

from db.blobs import PIXEL_DTYPE, TRACE_DTYPE, encode_array
from tests.support.db_fixtures import GRID, T0, sample_codes, sample_pixels
from uplink.contract import (
    AlertEventRecord,
    BaselineRecord,
    Blob,
    DetectionRecord,
    DiMapRecord,
    IngestBatch,
    MeasurementRecord,
    MeasurementSettings,
    NodeRecord,
    Record,
    StateChangeRecord,
    record_uid,
)


def blob(stored: bytes, dtype: str, *, send: bool = True) -> Blob:
    return Blob.of(stored if send else None, dtype=dtype, sha256=hashlib.sha256(stored).hexdigest(),  # type: ignore[arg-type]
                   nbytes=len(stored))


def node_record(gateway: str, node_id: str, *, seen_at: datetime = T0, state: str = "ok",
                **admin: object) -> NodeRecord:
    return NodeRecord(uid=record_uid(gateway, "node", node_id), node_id=node_id, firmware="1.4.2", protocol_version=2,
                      n_channels=8, fs_hz=2.0e6, geometry={"rx_angles_deg": [i * 45.0 for i in range(8)],
                                                           "tx_angles_deg": [0.0], "tx_rx_distance_mm": 500.0,
                                                           "circumference_mm": 690.8, "pipe_length_mm": 6000.0,
                                                           "tx_axial_mm": 1000.0},
                      first_seen_at=T0, last_seen_at=seen_at, online=True, state=state, **admin)  # type: ignore[arg-type]


def baseline_record(gateway: str, node_id: str, local_id: int, measurement_local_id: int, *, active: bool = True,
                    deactivated_at: datetime | None = None, reason: str = "commissioning") -> BaselineRecord:
    return BaselineRecord(uid=record_uid(gateway, "baseline", local_id), node_id=node_id,
                          measurement_uid=record_uid(gateway, "measurement", measurement_local_id), created_by="gateway",
                          created_at=T0, reason=reason, active=active, deactivated_at=deactivated_at)


def measurement_record(gateway: str, node_id: str, local_id: int, *, traces: bool = True, with_map: bool = False,
                       n_samples: int = 2048) -> MeasurementRecord:
    codes = encode_array(sample_codes(local_id, n_samples=n_samples), TRACE_DTYPE)
    maps = []
    if with_map:
        pixels = encode_array(sample_pixels(local_id), PIXEL_DTYPE)
        maps.append(DiMapRecord(source="gateway", method="delay-and-sum", grid=GRID.model_dump(mode="json"),
                                pixels=blob(pixels.data, PIXEL_DTYPE), peak_di=0.4,
                                created_at=T0 + timedelta(seconds=local_id)))
    return MeasurementRecord(
        uid=record_uid(gateway, "measurement", local_id), node_id=node_id, measurement_kind="monitor",
        acquired_at=T0 + timedelta(seconds=local_id), node_measurement_id=local_id,
        settings=MeasurementSettings(temperature_c=21.5, averaging=16, fs_hz=2.0e6, t0_s=1e-5, n_channels=8,
                                     n_samples=n_samples, volts_per_code=1 / 32768, excitation_hz=85e3, cycles=5),
        traces=blob(codes.data, TRACE_DTYPE, send=traces), di_maps=maps,
    )


def detection_record(gateway: str, node_id: str, local_id: int, measurement_local_id: int,
                     state: str = "damage") -> DetectionRecord:
    return DetectionRecord(uid=record_uid(gateway, "detection", local_id), node_id=node_id,
                           measurement_uid=record_uid(gateway, "measurement", measurement_local_id),
                           peak_di=0.4, threshold=0.1, axial_mm=1500.0, angle_deg=90.0,
                           state=state, created_at=T0 + timedelta(seconds=measurement_local_id))  # type: ignore[arg-type]


def state_change_record(gateway: str, node_id: str, local_id: int, measurement_local_id: int) -> StateChangeRecord:
    return StateChangeRecord(uid=record_uid(gateway, "state_change", local_id), node_id=node_id,
                             measurement_uid=record_uid(gateway, "measurement", measurement_local_id),
                             from_state="ok", to_state="damage", at=T0 + timedelta(seconds=measurement_local_id))


def alert_record(gateway: str, node_id: str, *, central: bool) -> AlertEventRecord:
    event_id = uuid.uuid4()
    return AlertEventRecord(uid=record_uid(gateway, "alert_event", event_id), event_id=event_id, node_id=node_id,
                            event_kind="damage_detected", severity="critical", payload={"node_id": node_id},
                            created_at=T0, deliver_centrally=central)


def batch_of(gateway: str, site: str, records: list[Record]) -> IngestBatch:
    return IngestBatch(gateway_id=gateway, site=site, batch_id=uuid.uuid4(), records=records)


def node_history(gateway: str, node_id: str, first_local_id: int, count: int, **measurement: object) -> list[Record]:
    """A node record, then ``count`` measurements each with its detection (ids from ``first_local_id``)."""
    records: list[Record] = [node_record(gateway, node_id)]
    for local_id in range(first_local_id, first_local_id + count):
        records.append(measurement_record(gateway, node_id, local_id, **measurement))  # type: ignore[arg-type]
        records.append(detection_record(gateway, node_id, local_id, local_id, state="ok"))
    return records
