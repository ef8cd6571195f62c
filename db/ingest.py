"""The central site's side of the uplink: one gateway's batch stored whole, each record once.

``ingest_batch`` runs inside one ``Database.write()``: every record of the batch is checked and
written in order, and the first one that is refused (another gateway's node, a reference to a
record the centre does not hold, a map without its pixels) raises :class:`IngestRefused` naming
it, so the transaction rolls back and nothing of the batch is kept. Records the centre already
holds (by their edge-made uid) are counted as duplicates and left untouched, so a retried or
replayed batch changes nothing; the exceptions are a measurement stored without its traces,
which takes them from a record of the same uid that carries them (traces on demand:
``uplink.contract.resent_measurement``, ``db.trace_requests``), and a baseline deactivated at the
gateway after it was sent (``uplink.contract.resent_baseline``: only ``active`` and
``deactivated_at`` change). A node record updates the node unless it is older than what the centre
holds (``uplink.contract.node_record_is_stale``: by revision, then ``last_seen_at``).
"""
from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Literal

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import StorageError
from db.models import (
    BaselineRow,
    DeliveryRow,
    DeliveryStatus,
    DetectionRow,
    DiMapRow,
    EventRow,
    IngestedRecordRow,
    MeasurementKind,
    MeasurementRow,
    NodeRow,
    NodeState,
    Severity,
    StateChangeRow,
)
from db.trace_requests import edge_record, mark_received
from uplink.contract import (
    AlertEventRecord,
    BaselineRecord,
    BaselineView,
    DetectionRecord,
    IngestBatch,
    MeasurementRecord,
    NodeRecord,
    StateChangeRecord,
    StoredTraces,
    node_record_is_stale,
    resent_baseline,
    resent_measurement,
)

EDGE_ORIGIN = "edge"
Refusal = Literal["invalid", "forbidden", "unknown-reference"]


class IngestRefused(StorageError):
    """The batch is refused whole because of one record (``index`` None: the batch itself)."""

    def __init__(self, reason: Refusal, error: str, *, index: int | None = None, uid: str | None = None,
                 kind: str | None = None) -> None:
        super().__init__(error if index is None else f"record {index} ({uid}): {error}")
        self.reason = reason
        self.error = error
        self.index = index
        self.uid = uid
        self.kind = kind


class _Refused(Exception):
    """Raised by the per-record steps; ``ingest_batch`` adds which record it was."""

    def __init__(self, reason: Refusal, error: str) -> None:
        super().__init__(error)
        self.reason: Refusal = reason
        self.error = error


@dataclass(frozen=True)
class IngestOutcome:
    accepted: int
    duplicates: int
    stale: int


# The node fields a node record sets (the rest of a NodeRow is the centre's own: details, link).
_NODE_FIELDS = ("firmware", "protocol_version", "n_channels", "fs_hz", "geometry", "first_seen_at", "last_seen_at",
                "online", "latest_di_peak", "latest_threshold", "label", "location", "decommissioned_at",
                "decommissioned_by", "decommission_reason")


class _Batch:
    def __init__(self, session: Session, batch: IngestBatch, now: datetime, alert_sinks: Sequence[str]) -> None:
        self.session = session
        self.batch = batch
        self.now = now
        self.alert_sinks = tuple(alert_sinks)
        self.central_ids: dict[str, str] = {}  # uid -> the row's id here, for references

    # --- ownership and references
    def own_node(self, node_id: str) -> NodeRow:
        node = self.session.get(NodeRow, node_id)
        if node is None:
            raise _Refused("unknown-reference", f"node {node_id!r} is not known here: send its node record first")
        self.check_owner(node)
        return node

    def check_owner(self, node: NodeRow) -> None:
        gateway, site = self.batch.gateway_id, self.batch.site
        if (node.gateway_id, node.site) != (gateway, site):
            owner = "this site itself" if node.gateway_id is None else f"gateway {node.gateway_id!r} of site {node.site!r}"
            raise _Refused("forbidden", f"node {node.node_id!r} belongs to {owner}, not to gateway {gateway!r}")

    def measurement_id(self, uid: str) -> int:
        prefix = f"{self.batch.gateway_id}/measurement/"
        if not uid.startswith(prefix):
            raise _Refused("forbidden", f"{uid!r} is not one of gateway {self.batch.gateway_id!r}'s measurements")
        return int(self.central_id(uid, "measurement"))

    def central_id(self, uid: str, kind: str) -> str:
        """The id here of the record ``uid`` (a ``kind``) held already; refused if it is not."""
        central = self.central_ids.get(uid)
        if central is None:
            row = self.session.get(IngestedRecordRow, uid)
            if row is None:
                raise _Refused("unknown-reference", f"{kind} {uid!r} is not known here: send it first")
            central = self.central_ids[uid] = row.central_id
        return central

    def remember(self, uid: str, kind: str, central_id: object) -> None:
        self.session.add(IngestedRecordRow(uid=uid, gateway_id=self.batch.gateway_id, kind=kind,
                                           central_id=str(central_id), batch_id=self.batch.batch_id,
                                           stored_at=self.now))
        self.central_ids[uid] = str(central_id)

    # --- the records
    def node(self, record: NodeRecord) -> Literal["accepted", "duplicate", "stale"]:
        values = {name: getattr(record, name) for name in _NODE_FIELDS}
        values["state"] = NodeState(record.state)
        values["source_revision"] = record.revision
        node = self.session.get(NodeRow, record.node_id)
        if node is None:
            self.session.add(NodeRow(node_id=record.node_id, port_url=f"uplink:{self.batch.gateway_id}",
                                     error_counters={}, site=self.batch.site, gateway_id=self.batch.gateway_id,
                                     watched_since=record.first_seen_at, **values))
            return "accepted"
        self.check_owner(node)
        if node_record_is_stale(node.source_revision, node.last_seen_at, record):
            return "stale"
        if all(getattr(node, name) == value for name, value in values.items()):
            return "duplicate"
        if node.decommissioned_at is not None and record.decommissioned_at is None:
            node.watched_since = self.now  # recommissioned: watched again from now, as at its gateway (db/nodes.py)
        for name, value in values.items():
            setattr(node, name, value)
        return "accepted"

    def measurement(self, record: MeasurementRecord) -> None:
        self.own_node(record.node_id)
        traces = record.traces
        stored = traces.raw() if traces.data is not None else None
        settings = record.settings
        row = MeasurementRow(
            node_id=record.node_id, kind=MeasurementKind(record.measurement_kind), acquired_at=record.acquired_at,
            node_measurement_id=record.node_measurement_id, temperature_c=settings.temperature_c,
            averaging=settings.averaging, fs_hz=settings.fs_hz, t0_s=settings.t0_s, n_channels=settings.n_channels,
            n_samples=settings.n_samples, volts_per_code=settings.volts_per_code,
            excitation_hz=settings.excitation_hz, cycles=settings.cycles, velocity_m_s=record.velocity_m_s,
            wall_mm=record.wall_mm, boot_id=record.boot_id, traces_blob=stored, traces_codec=traces.codec,
            traces_dtype=traces.dtype, traces_sha256=traces.sha256, traces_nbytes=traces.nbytes,
            # Traces the gateway does not send are, here, as if retention had pruned them.
            traces_pruned_at=None if stored is not None else self.now, stored_at=self.now,
        )
        self.session.add(row)
        self.session.flush()
        for position, di_map in enumerate(record.di_maps):
            if di_map.pixels.data is None:
                raise _Refused("invalid", f"di_maps[{position}]: a map's pixels must be sent")
            baseline = (None if di_map.baseline_measurement_uid is None
                        else self.measurement_id(di_map.baseline_measurement_uid))
            self.session.add(DiMapRow(
                measurement_id=row.id, source=di_map.source, method=di_map.method, grid=di_map.grid,
                baseline_measurement_id=baseline, pixels_blob=di_map.pixels.raw(), pixels_codec=di_map.pixels.codec,
                pixels_dtype=di_map.pixels.dtype, pixels_sha256=di_map.pixels.sha256, peak_di=di_map.peak_di,
                created_at=di_map.created_at,
            ))
        self.remember(record.uid, record.kind, row.id)

    def measurement_again(self, record: MeasurementRecord) -> Literal["accepted", "duplicate"]:
        """A measurement held already: its traces added if it lacks them and the record brings them."""
        if record.traces.data is None:
            return "duplicate"
        self.own_node(record.node_id)
        row = self.session.get(MeasurementRow, self.measurement_id(record.uid))
        if row is None or row.node_id != record.node_id:
            raise _Refused("invalid", f"measurement {record.uid!r} is not node {record.node_id!r}'s here")
        stored = StoredTraces(here=row.traces_pruned_at is None, codec=row.traces_codec, dtype=row.traces_dtype,
                              sha256=row.traces_sha256, nbytes=row.traces_nbytes)
        try:
            outcome = resent_measurement(stored, record)
        except ValueError as exc:
            raise _Refused("invalid", str(exc)) from None
        if outcome == "duplicate":
            return "duplicate"
        row.traces_blob = record.traces.raw()
        row.traces_pruned_at = None
        mark_received(self.session, row.id, now=self.now)
        return "accepted"

    def baseline(self, record: BaselineRecord) -> None:
        self.own_node(record.node_id)
        measurement_id = self.measurement_id(record.measurement_uid)
        if record.active:  # the edge's newer active baseline replaces the one sent before
            self.session.execute(
                update(BaselineRow)
                .where(BaselineRow.node_id == record.node_id, BaselineRow.active.is_(True))
                .values(active=False, deactivated_at=record.created_at)
                .execution_options(synchronize_session=False)
            )
        row = BaselineRow(node_id=record.node_id, measurement_id=measurement_id, created_by=record.created_by,
                          created_at=record.created_at, reason=record.reason, active=record.active,
                          deactivated_at=record.deactivated_at)
        self.session.add(row)
        self.session.flush()
        self.remember(record.uid, record.kind, row.id)

    def baseline_again(self, record: BaselineRecord) -> Literal["accepted", "duplicate", "stale"]:
        """A baseline held already: deactivated if the gateway deactivated it since; nothing else changes."""
        self.own_node(record.node_id)
        row = self.session.get(BaselineRow, int(self.central_id(record.uid, "baseline")))
        if row is None or row.node_id != record.node_id:
            raise _Refused("invalid", f"baseline {record.uid!r} is not node {record.node_id!r}'s here")
        stored = BaselineView(row.node_id, self.measurement_uid(row.measurement_id), row.created_by, row.created_at,
                              row.reason, row.active, row.deactivated_at)
        try:
            outcome = resent_baseline(stored, BaselineView.of(record))
        except ValueError as exc:
            raise _Refused("invalid", str(exc)) from None
        if outcome != "deactivate":
            return outcome
        row.active, row.deactivated_at = False, record.deactivated_at
        self.session.flush()
        return "accepted"

    def measurement_uid(self, measurement_id: int) -> str:
        """The edge's uid of a measurement held here."""
        edge = edge_record(self.session, measurement_id)
        return edge.uid if edge is not None else f"(measurement {measurement_id} here)"

    def detection(self, record: DetectionRecord) -> None:
        self.own_node(record.node_id)
        measurement_id = self.measurement_id(record.measurement_uid)
        if self.session.scalar(select(DetectionRow.id).where(DetectionRow.measurement_id == measurement_id)):
            raise _Refused("invalid", f"measurement {record.measurement_uid!r} already has a detection")
        row = DetectionRow(
            measurement_id=measurement_id, node_id=record.node_id,
            peak_di=record.peak_di, threshold=record.threshold, axial_mm=record.axial_mm, angle_deg=record.angle_deg,
            state=NodeState(record.state), confidence=record.confidence, method=record.method,
            defects=record.defects, sensor_faults=record.sensor_faults,
            baseline_measurement_id=(None if record.baseline_measurement_uid is None
                                     else self.measurement_id(record.baseline_measurement_uid)),
            stretch=record.stretch, abstain_reason=record.abstain_reason, created_at=record.created_at,
        )
        self.session.add(row)
        self.session.flush()
        self.remember(record.uid, record.kind, row.id)

    def state_change(self, record: StateChangeRecord) -> None:
        self.own_node(record.node_id)
        row = StateChangeRow(
            node_id=record.node_id,
            measurement_id=None if record.measurement_uid is None else self.measurement_id(record.measurement_uid),
            from_state=NodeState(record.from_state), to_state=NodeState(record.to_state), at=record.at,
        )
        self.session.add(row)
        self.session.flush()
        self.remember(record.uid, record.kind, row.id)

    def alert_event(self, record: AlertEventRecord) -> None:
        if record.node_id is not None:
            self.own_node(record.node_id)
        if self.session.get(EventRow, record.event_id) is not None:
            raise _Refused("forbidden", f"event {record.event_id} is already held here under another uid")
        row = EventRow(id=record.event_id, node_id=record.node_id, kind=record.event_kind,
                       severity=Severity(record.severity), payload=dict(record.payload),
                       created_at=record.created_at, origin=EDGE_ORIGIN)
        # The centre's sinks send only what the gateway left to them (docs/alerting.md).
        sinks = self.alert_sinks if record.deliver_centrally else ()
        row.deliveries = [DeliveryRow(sink=sink, status=DeliveryStatus.PENDING, attempts=0, next_attempt_at=self.now,
                                      last_error=None) for sink in sinks]
        self.session.add(row)
        self.session.flush()
        self.remember(record.uid, record.kind, record.event_id)


def ingest_batch(session: Session, batch: IngestBatch, *, key_site: str, alert_sinks: Sequence[str] = (),
                 now: datetime | None = None) -> IngestOutcome:
    """Store ``batch`` from a gateway whose key is scoped to ``key_site``; raises :class:`IngestRefused`.

    ``alert_sinks``: the centre's sinks, given a pending delivery for each alert event the gateway
    leaves to the centre (``deliver_centrally``). Call inside ``Database.write()``.
    """
    if batch.site != key_site:
        raise IngestRefused("forbidden", f"this key writes for site {key_site!r}, the batch is for site {batch.site!r}")
    work = _Batch(session, batch, now or utc_now(), alert_sinks)
    uids = [record.uid for record in batch.records if record.kind != "node"]
    held = set(session.scalars(select(IngestedRecordRow.uid).where(IngestedRecordRow.uid.in_(uids)))) if uids else set()
    accepted = duplicates = stale = 0
    for index, record in enumerate(batch.records):
        try:
            if isinstance(record, NodeRecord):
                outcome = work.node(record)
                session.flush()
            elif record.uid in held:
                if isinstance(record, MeasurementRecord):
                    outcome = work.measurement_again(record)
                elif isinstance(record, BaselineRecord):
                    outcome = work.baseline_again(record)
                else:
                    outcome = "duplicate"
            else:
                getattr(work, record.kind)(record)
                outcome = "accepted"
        except _Refused as refused:
            raise IngestRefused(refused.reason, refused.error, index=index, uid=record.uid, kind=record.kind) from None
        accepted += outcome == "accepted"
        duplicates += outcome == "duplicate"
        stale += outcome == "stale"
    session.flush()
    return IngestOutcome(accepted=accepted, duplicates=duplicates, stale=stale)


def edge_event_ids(session: Session) -> set[uuid.UUID]:
    """Ids of the alert events ingested from gateways (for tests and reports)."""
    return set(session.scalars(select(EventRow.id).where(EventRow.origin == EDGE_ORIGIN)))
