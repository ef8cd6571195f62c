"""ORM models (SQLAlchemy 2.0 typed declarative). The schema itself is made by Alembic.

Rows are named ``...Row`` so they are never mistaken for the in-memory records of
``imaging``/``protocol``. Every timestamp is a timezone-aware UTC instant.
"""
from __future__ import annotations

import uuid
from datetime import datetime
from enum import StrEnum
from typing import Any, ClassVar

from sqlalchemy import (
    BigInteger,
    Boolean,
    CheckConstraint,
    Enum,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    Uuid,
    false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

from db.column_types import BigId, UTCDateTime, json_type

# Deterministic constraint names, so migrations can refer to them on every backend.
NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class NodeState(StrEnum):
    COMMISSIONING = "commissioning"  # collecting its first baseline(s)
    CALIBRATING = "calibrating"  # collecting baseline-condition DI peaks for its threshold
    OK = "ok"
    SUSPECTED = "suspected"
    DAMAGE = "damage"
    NO_VALID_BASELINE = "no_valid_baseline"


class MeasurementKind(StrEnum):
    BASELINE = "baseline"
    MONITOR = "monitor"


class MapSource(StrEnum):
    NODE = "node"  # computed on the FPGA node and sent with the traces
    GATEWAY = "gateway"  # recomputed by the gateway from the raw traces


class Severity(StrEnum):
    INFO = "info"
    WARNING = "warning"
    CRITICAL = "critical"


class DeliveryStatus(StrEnum):
    PENDING = "pending"
    DELIVERED = "delivered"
    DEAD = "dead"


class UplinkKind(StrEnum):
    """What a record of the uplink queue replicates (the wire contract's record kinds)."""

    NODE = "node"
    MEASUREMENT = "measurement"
    BASELINE = "baseline"
    DETECTION = "detection"
    STATE_CHANGE = "state_change"
    ALERT_EVENT = "alert_event"


class UplinkStatus(StrEnum):
    PENDING = "pending"  # not yet acknowledged by the centre
    SENT = "sent"  # the centre acknowledged it (accepted, or already held it)
    REFUSED = "refused"  # the centre refused it as malformed: kept here, never retried on its own


class TraceRequestStatus(StrEnum):
    """Where a central operator's request for a measurement's raw traces stands (revision 0009)."""

    REQUESTED = "requested"  # recorded here, the gateway has not answered yet
    HELD = "held"  # the gateway holds the traces and has queued them for upload
    RECEIVED = "received"  # the traces arrived and were added to the measurement
    PRUNED = "pruned"  # the gateway answered that it no longer holds them
    REFUSED = "refused"  # the gateway re-sent the measurement and this site refused the record (revision 0012)


class Role(StrEnum):
    VIEWER = "viewer"
    OPERATOR = "operator"
    ADMIN = "admin"
    GATEWAY = "gateway"  # a gateway reporting to the central site: ingest only, its own site only


def _enum(enum_cls: type[StrEnum], name: str) -> Enum:
    """A portable enum column: VARCHAR plus a named CHECK constraint, no native PG type."""
    return Enum(
        enum_cls,
        name=name,
        native_enum=False,
        create_constraint=True,
        length=32,
        values_callable=lambda members: [member.value for member in members],
        validate_strings=True,
    )


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {datetime: UTCDateTime(), dict[str, Any]: json_type()}


class NodeRow(Base):
    """One FPGA node as last reported by its INFO message, plus the gateway's view of it.

    A configured node is registered when the gateway starts (revision 0010), before it answers:
    until its first INFO what INFO tells is unknown (NULL) and it was never seen
    (``last_seen_at`` NULL, :attr:`never_seen`); ``watched_since`` is when it was registered.
    """

    __tablename__ = "nodes"
    __table_args__ = (Index("ix_nodes_site_gateway_id", "site", "gateway_id"),)

    node_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    port_url: Mapped[str] = mapped_column(String(255))
    # From INFO; NULL until the node's first INFO (revision 0010).
    firmware: Mapped[str | None] = mapped_column(String(64))
    protocol_version: Mapped[int | None] = mapped_column(Integer)
    n_channels: Mapped[int | None] = mapped_column(Integer)
    fs_hz: Mapped[float | None] = mapped_column(Float)
    # ring angles, tx_rx_distance_mm, circumference_mm, pipe_length_mm, tx_axial_mm
    geometry: Mapped[dict[str, Any] | None] = mapped_column(json_type())
    watched_since: Mapped[datetime]  # registered: at the gateway's start, or at its first INFO (revision 0010)
    first_seen_at: Mapped[datetime | None]
    last_seen_at: Mapped[datetime | None]  # NULL: never answered
    online: Mapped[bool] = mapped_column(Boolean, server_default=false())
    error_counters: Mapped[dict[str, Any]]
    state: Mapped[NodeState] = mapped_column(_enum(NodeState, "node_state"))
    latest_di_peak: Mapped[float | None] = mapped_column(Float)
    latest_threshold: Mapped[float | None] = mapped_column(Float)
    # Set by an admin through the API (revision 0002): how people name and find the node.
    label: Mapped[str | None] = mapped_column(String(128))
    location: Mapped[str | None] = mapped_column(String(256))
    notes: Mapped[str | None] = mapped_column(Text)
    details_updated_at: Mapped[datetime | None]
    details_updated_by: Mapped[str | None] = mapped_column(String(128))
    # A decommissioned node is not polled and raises no outage alert; its history is kept.
    decommissioned_at: Mapped[datetime | None]
    decommissioned_by: Mapped[str | None] = mapped_column(String(128))
    decommission_reason: Mapped[str | None] = mapped_column(Text)
    # The link as the gateway last found it (revision 0005): who answers on the port, its boot,
    # the settings it applied, and how either differs from the configuration.
    reported_node_id: Mapped[str | None] = mapped_column(String(64))  # INFO's node_id
    boot_id: Mapped[int | None] = mapped_column(BigInteger)
    reboots: Mapped[int] = mapped_column(Integer, server_default="0")  # that the gateway noticed
    last_reboot_at: Mapped[datetime | None]
    applied_settings: Mapped[dict[str, Any] | None] = mapped_column(json_type())  # CONFIGURE_REPLY
    link_problems: Mapped[list[Any] | None] = mapped_column(json_type())  # identity, settings not applied
    # At the central site (revision 0006): where the node reports from; NULL on a gateway's own database.
    site: Mapped[str | None] = mapped_column(String(64))
    gateway_id: Mapped[str | None] = mapped_column(String(64))
    # Revision 0011: this database's count of changes to the node's replicated view (an INFO, an admin's
    # details, (re)commissioning), carried by its node record; at the central site, the revision of the
    # gateway's node record last applied (NULL: none, or a gateway that sends none).
    revision: Mapped[int] = mapped_column(Integer, server_default="0")
    source_revision: Mapped[int | None] = mapped_column(Integer)

    @property
    def never_seen(self) -> bool:
        """Registered from the configuration, and has not answered yet."""
        return self.last_seen_at is None


class MeasurementRow(Base):
    """One acquisition: metadata always; raw ADC codes until retention prunes them."""

    __tablename__ = "measurements"
    __table_args__ = (
        Index("ix_measurements_node_time", "node_id", "acquired_at", "id"),
        Index("ix_measurements_node_id_order", "node_id", "id"),  # lists and "latest" go by insertion
        # A blob is either present (not pruned) or gone with the time it was pruned.
        CheckConstraint(
            "(traces_blob IS NULL) = (traces_pruned_at IS NOT NULL)", name="traces_xor_pruned"
        ),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    node_id: Mapped[str] = mapped_column(ForeignKey("nodes.node_id"))
    kind: Mapped[MeasurementKind] = mapped_column(_enum(MeasurementKind, "measurement_kind"))
    acquired_at: Mapped[datetime]
    node_measurement_id: Mapped[int] = mapped_column(Integer)
    temperature_c: Mapped[float | None] = mapped_column(Float)
    averaging: Mapped[int] = mapped_column(Integer)
    fs_hz: Mapped[float] = mapped_column(Float)
    t0_s: Mapped[float] = mapped_column(Float)
    n_channels: Mapped[int] = mapped_column(Integer)
    n_samples: Mapped[int] = mapped_column(Integer)
    volts_per_code: Mapped[float] = mapped_column(Float)
    excitation_hz: Mapped[float] = mapped_column(Float)
    cycles: Mapped[int] = mapped_column(Integer)
    # What the gateway imaged the record with (revision 0004; NULL before: the default velocity, no wall).
    velocity_m_s: Mapped[float | None] = mapped_column(Float)
    wall_mm: Mapped[float | None] = mapped_column(Float)
    boot_id: Mapped[int | None] = mapped_column(BigInteger)  # the node's boot it was taken in (revision 0005)
    # Deferred: listing measurements must not drag ~100 kB per row out of the database.
    traces_blob: Mapped[bytes | None] = mapped_column(LargeBinary, deferred=True)
    traces_codec: Mapped[str] = mapped_column(String(32))
    traces_dtype: Mapped[str] = mapped_column(String(8))
    traces_sha256: Mapped[str] = mapped_column(String(64))
    traces_nbytes: Mapped[int] = mapped_column(Integer)
    traces_pruned_at: Mapped[datetime | None]
    stored_at: Mapped[datetime]

    node: Mapped[NodeRow] = relationship()
    di_maps: Mapped[list[DiMapRow]] = relationship(
        back_populates="measurement",
        foreign_keys="DiMapRow.measurement_id",
        order_by="DiMapRow.id",
    )


class DiMapRow(Base):
    """A damage-index image of one monitor measurement against a baseline."""

    __tablename__ = "di_maps"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    measurement_id: Mapped[int] = mapped_column(BigId, ForeignKey("measurements.id"), index=True)
    source: Mapped[MapSource] = mapped_column(_enum(MapSource, "map_source"))
    method: Mapped[str] = mapped_column(String(64))
    # axial_start_mm/axial_step_mm/axial_count, angle_start_deg/angle_step_deg/angle_count
    grid: Mapped[dict[str, Any]]
    baseline_measurement_id: Mapped[int | None] = mapped_column(BigId, ForeignKey("measurements.id"))
    pixels_blob: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)
    pixels_codec: Mapped[str] = mapped_column(String(32))
    pixels_dtype: Mapped[str] = mapped_column(String(8))
    pixels_sha256: Mapped[str] = mapped_column(String(64))
    peak_di: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime]

    measurement: Mapped[MeasurementRow] = relationship(
        back_populates="di_maps", foreign_keys=[measurement_id]
    )


class BaselineRow(Base):
    """Which measurement a node's DI maps are computed against; the history is kept."""

    __tablename__ = "baselines"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    node_id: Mapped[str] = mapped_column(ForeignKey("nodes.node_id"), index=True)
    measurement_id: Mapped[int] = mapped_column(BigId, ForeignKey("measurements.id"), index=True)
    created_by: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime]
    reason: Mapped[str] = mapped_column(Text)
    active: Mapped[bool] = mapped_column(Boolean)
    deactivated_at: Mapped[datetime | None]


# At most one active baseline per node, enforced by the database as well as by
# set_active_baseline(); both SQLite (>= 3.8) and PostgreSQL support partial indexes.
Index(
    "uq_baselines_one_active_per_node",
    BaselineRow.node_id,
    unique=True,
    sqlite_where=BaselineRow.active,
    postgresql_where=BaselineRow.active,
)


class DetectionRow(Base):
    """The verdict on one monitor measurement: DI peak against threshold, and where.

    ``peak_di`` is None when the imaging abstained (no baseline matched the conditions).
    ``axial_mm``/``angle_deg``/``confidence`` are the map's peak; ``defects`` lists every
    defect found above the threshold ({axial_mm, angle_deg, di, severity, confidence}).
    """

    __tablename__ = "detections"
    __table_args__ = (
        Index("ix_detections_node_time", "node_id", "created_at", "id"),
        Index("ix_detections_node_id_order", "node_id", "id"),  # lists and "latest" go by insertion
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    measurement_id: Mapped[int] = mapped_column(BigId, ForeignKey("measurements.id"), unique=True)
    node_id: Mapped[str] = mapped_column(ForeignKey("nodes.node_id"))
    peak_di: Mapped[float | None] = mapped_column(Float)
    threshold: Mapped[float | None] = mapped_column(Float)  # None while the threshold is being calibrated
    axial_mm: Mapped[float | None] = mapped_column(Float)
    angle_deg: Mapped[float | None] = mapped_column(Float)
    state: Mapped[NodeState] = mapped_column(_enum(NodeState, "detection_state"))
    confidence: Mapped[float | None] = mapped_column(Float)
    method: Mapped[str | None] = mapped_column(String(32))
    defects: Mapped[list[Any] | None] = mapped_column(json_type())
    sensor_faults: Mapped[list[Any] | None] = mapped_column(json_type())
    baseline_measurement_id: Mapped[int | None] = mapped_column(BigId, ForeignKey("measurements.id"))
    stretch: Mapped[float | None] = mapped_column(Float)  # baseline time-stretch factor used (BSS)
    abstain_reason: Mapped[str | None] = mapped_column(Text)  # why no map was made (peak_di is null)
    created_at: Mapped[datetime]


class StateChangeRow(Base):
    """A transition of a node's state, with the measurement that caused it (if any)."""

    __tablename__ = "state_changes"
    __table_args__ = (
        Index("ix_state_changes_node_time", "node_id", "at", "id"),
        Index("ix_state_changes_node_id_order", "node_id", "id"),  # the history goes by insertion
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    node_id: Mapped[str] = mapped_column(ForeignKey("nodes.node_id"))
    measurement_id: Mapped[int | None] = mapped_column(BigId, ForeignKey("measurements.id"))
    from_state: Mapped[NodeState] = mapped_column(_enum(NodeState, "from_state"))
    to_state: Mapped[NodeState] = mapped_column(_enum(NodeState, "to_state"))
    at: Mapped[datetime]


class EventRow(Base):
    """The alert outbox: written in the same transaction as the fact it reports."""

    __tablename__ = "events"
    __table_args__ = (Index("ix_events_created_at", "created_at"),)

    id: Mapped[uuid.UUID] = mapped_column(Uuid, primary_key=True)
    node_id: Mapped[str | None] = mapped_column(ForeignKey("nodes.node_id"), index=True)
    kind: Mapped[str] = mapped_column(String(64))
    severity: Mapped[Severity] = mapped_column(_enum(Severity, "severity"))
    payload: Mapped[dict[str, Any]]
    created_at: Mapped[datetime]
    # An operator's handling of the alert (API: acknowledge, resolve); delivery is tracked per sink.
    acknowledged_at: Mapped[datetime | None]
    acknowledged_by: Mapped[str | None] = mapped_column(String(128))
    resolved_at: Mapped[datetime | None]
    resolved_by: Mapped[str | None] = mapped_column(String(128))
    # "edge": ingested from a gateway (revision 0006; docs/alerting.md says who sends it); NULL: raised here.
    origin: Mapped[str | None] = mapped_column(String(16))

    deliveries: Mapped[list[DeliveryRow]] = relationship(back_populates="event", order_by="DeliveryRow.id")


class DeliveryRow(Base):
    """One event's delivery state towards one sink (webhook, MQTT, ...)."""

    __tablename__ = "deliveries"
    __table_args__ = (
        UniqueConstraint("event_id", "sink"),
        Index("ix_deliveries_due", "status", "next_attempt_at"),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    event_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("events.id"))
    sink: Mapped[str] = mapped_column(String(64))
    status: Mapped[DeliveryStatus] = mapped_column(_enum(DeliveryStatus, "delivery_status"))
    attempts: Mapped[int] = mapped_column(Integer)
    next_attempt_at: Mapped[datetime | None]
    last_error: Mapped[str | None] = mapped_column(Text)

    event: Mapped[EventRow] = relationship(back_populates="deliveries")


class ApiKeyRow(Base):
    """An API key: only the SHA-256 of the token and a short display prefix are stored."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    name: Mapped[str] = mapped_column(String(128))
    role: Mapped[Role] = mapped_column(_enum(Role, "role"))
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    key_prefix: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime]
    revoked_at: Mapped[datetime | None]
    site: Mapped[str | None] = mapped_column(String(64))  # a gateway key's site (revision 0006)


class IngestedRecordRow(Base):
    """A record the central site received from an edge, by its edge-made uid: stored once, ever."""

    __tablename__ = "ingested_records"
    __table_args__ = (Index("ix_ingested_records_kind_central_id", "kind", "central_id"),)  # (revision 0009)

    uid: Mapped[str] = mapped_column(String(200), primary_key=True)
    gateway_id: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(32))
    central_id: Mapped[str] = mapped_column(String(64))  # the row's id here (a measurement's, an event's, ...)
    batch_id: Mapped[uuid.UUID] = mapped_column(Uuid)
    stored_at: Mapped[datetime]


class UplinkRow(Base):
    """The uplink queue: one record to replicate to the central PipeSentry (revision 0008).

    Written in the same transaction as the fact it replicates (``db.uplink_queue``), sent in
    ``id`` order per node, marked ``sent`` once the centre acknowledged it. Retention keeps the
    raw traces of a measurement while a record that is to carry them is not sent.
    """

    __tablename__ = "uplink_queue"
    __table_args__ = (
        Index("ix_uplink_queue_status_node", "status", "node_id", "id"),
        Index("ix_uplink_queue_node_kind", "node_id", "kind", "id"),
        Index("ix_uplink_queue_measurement", "measurement_id"),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    kind: Mapped[UplinkKind] = mapped_column(_enum(UplinkKind, "uplink_kind"))
    node_id: Mapped[str | None] = mapped_column(ForeignKey("nodes.node_id"))  # None: a gateway-wide alert event
    ref: Mapped[str] = mapped_column(String(64))  # the local id of the replicated row (the uid's last part)
    measurement_id: Mapped[int | None] = mapped_column(BigId, ForeignKey("measurements.id"))
    with_traces: Mapped[bool] = mapped_column(Boolean, server_default=false())  # a measurement sent with its traces
    created_at: Mapped[datetime]
    status: Mapped[UplinkStatus] = mapped_column(_enum(UplinkStatus, "uplink_status"))
    sent_at: Mapped[datetime | None]
    refusals: Mapped[int] = mapped_column(Integer, server_default="0")
    last_error: Mapped[str | None] = mapped_column(Text)


class TraceRequestRow(Base):
    """A central operator's request for the raw traces of a measurement a gateway sent without them
    (revision 0009): one per measurement, asked again on the same row. The gateway polls for the
    ``requested`` ones of its site and answers ``held`` or ``pruned``; ingest marks it ``received``, or
    ``refused`` (with why, revision 0012) when it refuses the record the gateway re-sent."""

    __tablename__ = "trace_requests"
    __table_args__ = (Index("ix_trace_requests_pending", "site", "gateway_id", "status", "id"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    measurement_id: Mapped[int] = mapped_column(BigId, ForeignKey("measurements.id"), unique=True)
    measurement_uid: Mapped[str] = mapped_column(String(200))  # the edge's uid of the measurement
    gateway_id: Mapped[str] = mapped_column(String(64))
    site: Mapped[str] = mapped_column(String(64))
    status: Mapped[TraceRequestStatus] = mapped_column(_enum(TraceRequestStatus, "trace_request_status"))
    requested_by: Mapped[str] = mapped_column(String(128))  # the API key's name
    requested_at: Mapped[datetime]
    answered_at: Mapped[datetime | None]  # when the gateway answered held or pruned
    received_at: Mapped[datetime | None]
    refused_at: Mapped[datetime | None]  # when this site last refused the re-sent record (status refused)
    refusal: Mapped[str | None] = mapped_column(Text)  # why: the refusal the ingest answered the gateway


class UplinkConfigRow(Base):
    """One row while the gateway owning this database replicates to a centre (revision 0011): its
    ``send`` policy, so every process writing the database (the gateway's API too) queues what it
    changes (``db.uplink_queue.queue_policy``). No row: nothing queues."""

    __tablename__ = "uplink_config"
    __table_args__ = (
        CheckConstraint("id = 1", name="one_row"),
        CheckConstraint("send IN ('everything', 'flagged_traces')", name="send"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    send: Mapped[str] = mapped_column(String(32))
    since: Mapped[datetime]
