"""Typed response and request bodies of the API (what the OpenAPI schema documents)."""
from __future__ import annotations

import uuid
from datetime import datetime
from enum import StrEnum
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from db.models import DeliveryStatus, MapSource, MeasurementKind, NodeState, Role, Severity

# Ids up to 2**53 - 1: every JSON reader (JavaScript numbers, float-parsing clients) holds them
# exactly; with 2**62 a client's rounded 4.6e18 could land just past the bound.
MAX_ID = 2**53 - 1


class _Out(BaseModel):
    model_config = ConfigDict(from_attributes=True)


class Geometry(_Out):
    rx_angles_deg: list[float] = Field(description="receiver angles on the circumference, row i of the traces")
    tx_angles_deg: list[float]
    tx_rx_distance_mm: float = Field(description="axial distance between the Tx and Rx rings")
    circumference_mm: float
    pipe_length_mm: float | None = None
    tx_axial_mm: float | None = Field(None, description="Tx ring position from the pipe end behind it")


class AppliedSettings(_Out):
    """The acquisition settings the node said it applied (its CONFIGURE_REPLY)."""

    excitation_hz: float
    cycles: int
    averaging: int
    channel_mask: int
    n_samples: int


class Health(_Out):
    online: bool = Field(description="the node answered its last poll")
    never_seen: bool = Field(False, description="the node is configured but has never answered (first_seen_at, "
                             "last_seen_at and what INFO tells are null until it does)")
    watched_since: datetime | None = Field(None, description="when the gateway started watching the node (its "
                                           "start, for a node of its configuration; else the node's first answer)")
    first_seen_at: datetime | None = Field(description="the node's first answer (null: never seen)")
    last_seen_at: datetime | None = Field(description="when the node last answered (null: never seen)")
    reported_node_id: str | None = Field(
        None, description="the node_id the node on the port reports (INFO); records are stored only when it is "
        "this node's id")
    boot_id: int | None = Field(None, description="the node's boot id as last seen (docs/protocol.md 3.3)")
    reboots: int = Field(0, description="reboots the gateway noticed (a new boot id on an open port)")
    last_reboot_at: datetime | None = None
    applied_settings: AppliedSettings | None = Field(None, description="what the node runs since its last CONFIGURE")
    problems: list[str] = Field(
        default_factory=list, description="how the node differs from its configuration: another node_id on the "
        "port (nothing stored), settings the node did not apply (records stored with what it states)")


class Baseline(_Out):
    id: int
    node_id: str
    measurement_id: int = Field(description="the measurement DI maps are computed against")
    created_by: str = Field(description="who: 'gateway' or the name of the API key")
    created_at: datetime
    reason: str
    active: bool
    deactivated_at: datetime | None


class LocalizationRegion(BaseModel):
    """Where the defect lies with the stated probability: |axial error| <= axial_half_mm and |error round
    the pipe| <= circumferential_half_mm (imaging/region.py; calibrated on full-wave data, docs/accuracy.md)."""

    coverage: float = Field(0.9, description="probability that the region holds the defect")
    axial_half_mm: float = Field(description="half-width along the axis")
    circumferential_half_mm: float = Field(description="half-width round the pipe, as arc on the wall")
    localized: bool = Field(True, description="false: the map does not resolve the position (see reason); the "
                            "region then spans what the evidence leaves open")
    reason: str | None = Field(None, description="why the position is not resolved")


class DefectEstimate(BaseModel):
    """One defect found above the threshold (the strongest first)."""

    axial_mm: float = Field(description="axial distance from the Tx ring")
    angle_deg: float = Field(description="angle on the circumference, [0, 360)")
    di: float | None = Field(None, description="its DI")
    severity: float | None = Field(None, description="scattered amplitude relative to the direct arrival")
    confidence: dict[str, float | None] | None = Field(None, description="score in [0, 1], peak ratio, peak widths")
    region: LocalizationRegion | None = Field(None, description="its 90 % localization region (null: stored "
                                              "before regions were computed)")


class SensorFault(BaseModel):
    """A receiver channel whose direct arrival no longer matches its baseline: left out of the map."""

    rx_index: int
    rx_angle_deg: float | None = None
    kind: str = Field(description="no_signal, amplitude or timing")
    amplitude_ratio: float | None = None
    delay_s: float | None = None


class Detection(_Out):
    """The verdict on one monitor measurement and the estimated defect position."""

    id: int
    node_id: str
    measurement_id: int
    created_at: datetime
    peak_di: float | None = Field(
        description="peak of the gateway's DI map; null when the imaging abstained (no valid baseline)"
    )
    threshold: float | None = Field(description="damage threshold; null while the node is calibrating")
    state: NodeState = Field(description="node state after this measurement")
    axial_mm: float | None = Field(description="the map's peak: axial distance from the Tx ring")
    angle_deg: float | None = Field(description="the map's peak: angle on the circumference")
    confidence: float | None
    method: str | None = Field(None, description="imaging method: multipath or paper")
    defects: list[DefectEstimate] = Field(default_factory=list, description="every defect above the threshold")
    sensor_faults: list[SensorFault] = Field(default_factory=list, description="receivers left out of the map")
    baseline_measurement_id: int | None = Field(None, description="the library baseline the map was made against")
    stretch: float | None = Field(None, description="time-stretch applied to that baseline (temperature compensation)")
    abstain_reason: str | None = Field(None, description="why no map was made (peak_di is null), e.g. the record "
                                       "is further in temperature from every baseline than compensation covers")

    @field_validator("defects", "sensor_faults", mode="before")
    @classmethod
    def _none_is_empty(cls, value: Any) -> Any:
        return [] if value is None else value


class NodeDetails(_Out):
    """What people call the node and where it is (set by an admin); null until set."""

    label: str | None = Field(description="a name people recognise, e.g. 'Line 3, east loop'")
    location: str | None
    notes: str | None
    updated_at: datetime | None
    updated_by: str | None = Field(description="the API key name of the admin who last changed them")


class Decommissioned(_Out):
    """Why the node is out of service: it is not polled and raises no outage alert; its history stays."""

    at: datetime
    by: str
    reason: str


class Node(_Out):
    node_id: str
    details: NodeDetails
    decommissioned: Decommissioned | None = Field(description="null while the node is in service")
    port_url: str
    # From the node's INFO: null while it has never answered (health.never_seen).
    firmware: str | None = Field(description="null: never seen")
    protocol_version: int | None = Field(description="null: never seen")
    n_channels: int | None = Field(description="null: never seen")
    fs_hz: float | None = Field(description="null: never seen")
    geometry: Geometry | None = Field(description="null: never seen (unknown until its INFO)")
    health: Health
    error_counters: dict[str, int] = Field(description="serial-link and gateway counters, as last polled")
    state: NodeState
    latest_di_peak: float | None
    latest_threshold: float | None
    active_baseline: Baseline | None
    latest_detection: Detection | None
    site: str | None = Field(None, description="central site: the site the node reports from (null: this gateway's own)")
    gateway_id: str | None = Field(None, description="central site: the gateway that reports it (null: this one)")


class FleetNode(Node):
    state_since: datetime | None = Field(description="when the node entered its current state (null: never changed)")


class FleetNodePage(BaseModel):
    items: list[FleetNode]
    next_cursor: str | None


class SiteSummary(BaseModel):
    site: str | None = Field(description="null: the nodes without a site (a gateway's own)")
    gateways: list[str]
    nodes: int = Field(description="nodes in service")
    flagged: int = Field(description="nodes in damage or suspected")
    offline: int
    by_state: dict[str, int]
    last_seen_at: datetime | None


class DiMapSummary(_Out):
    id: int
    source: MapSource = Field(description="node: computed on the FPGA; gateway: recomputed from the raw traces")
    method: str
    peak_di: float
    baseline_measurement_id: int | None
    created_at: datetime


class MeasurementSummary(_Out):
    id: int
    node_id: str
    kind: MeasurementKind
    acquired_at: datetime
    node_measurement_id: int
    temperature_c: float | None
    n_channels: int
    n_samples: int
    traces_available: bool = Field(description="false once retention pruned the raw traces")


TracesStatusName = Literal["stored", "received", "requested", "held", "pruned", "refused", "at_gateway",
                           "pruned_here"]


class TracesState(_Out):
    """Where a measurement's raw traces are, and the central operator's request for them if there is one."""

    status: TracesStatusName = Field(
        description="stored: here; received: here, after a request; requested: asked, the gateway has not answered; "
        "held: the gateway holds them and has queued them for upload; pruned: the gateway answered it no longer "
        "holds them; refused: the gateway re-sent the measurement with them and this site refused the record "
        "(why: refusal; asking again is allowed); at_gateway: a gateway sent the measurement without them (its uplink policy), ask with POST "
        ".../traces/request; pruned_here: retention here removed them and no gateway has them to send")
    gateway_id: str | None = Field(description="the gateway that sent the measurement; null: this site's own")
    measurement_uid: str | None = Field(description="the measurement's uid at its gateway")
    requested_by: str | None = Field(description="the name of the key that asked for the traces")
    requested_at: datetime | None
    answered_at: datetime | None = Field(description="when the gateway answered held or pruned")
    received_at: datetime | None
    refused_at: datetime | None = Field(description="when this site refused the record the gateway re-sent with "
                                                    "the traces (status refused)")
    refusal: str | None = Field(description="why: the refusal the centre answered the gateway, e.g. HTTP 422 "
                                            "ingest-bad-record: traces (sha256 ...) are not the stored measurement's")


class Measurement(MeasurementSummary):
    averaging: int
    fs_hz: float
    t0_s: float
    volts_per_code: float
    excitation_hz: float
    cycles: int
    traces_pruned_at: datetime | None
    stored_at: datetime
    di_maps: list[DiMapSummary]
    detection: Detection | None
    traces: TracesState


class MeasurementPage(BaseModel):
    items: list[MeasurementSummary]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last page")


class DetectionPage(BaseModel):
    items: list[Detection]
    next_cursor: str | None


class TraceUnits(StrEnum):
    VOLTS = "volts"
    CODES = "codes"


class Traces(BaseModel):
    measurement_id: int
    units: TraceUnits
    fs_hz: float
    t0_s: float = Field(description="time of sample 0 relative to the excitation start")
    volts_per_code: float
    rx_angles_deg: list[float]
    traces: list[list[float]] = Field(description="[n_channels][n_samples]")


class Grid(BaseModel):
    axial_start_mm: float
    axial_step_mm: float
    axial_count: int
    angle_start_deg: float
    angle_step_deg: float
    angle_count: int


class Estimate(BaseModel):
    axial_mm: float = Field(description="axial distance from the Tx ring")
    angle_deg: float
    di: float | None


class DiMap(DiMapSummary):
    measurement_id: int
    grid: Grid
    pixels: list[list[float | None]] = Field(description="[axial_count][angle_count]; null for a non-finite pixel")
    estimate: Estimate | None = Field(description="the estimated defect position on this map")


class BaselineCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    measurement_id: int = Field(ge=1, le=MAX_ID)
    reason: str = Field(min_length=1, max_length=2000, description="why (kept in the history)")
    activate: bool = Field(True, description="make it the node's active baseline now")


class NodeDetailsUpdate(BaseModel):
    """Only the fields present are changed; null clears one."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"minProperties": 1})

    label: str | None = Field(None, min_length=1, max_length=128)
    location: str | None = Field(None, min_length=1, max_length=256)
    notes: str | None = Field(None, min_length=1, max_length=4000)

    @model_validator(mode="after")
    def _changes_something(self) -> NodeDetailsUpdate:
        if not self.model_fields_set:
            raise ValueError("name at least one of label, location, notes (null clears one)")
        return self


class NodeDecommission(BaseModel):
    model_config = ConfigDict(extra="forbid")

    reason: str = Field(min_length=1, max_length=2000, description="why (kept on the node)")


class BaselineActivate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    reason: str = Field(min_length=1, max_length=2000)


class AlertStatus(StrEnum):
    OPEN = "open"
    ACKNOWLEDGED = "acknowledged"
    RESOLVED = "resolved"


class Delivery(_Out):
    sink: str
    status: DeliveryStatus
    attempts: int
    next_attempt_at: datetime | None
    last_error: str | None


class Alert(_Out):
    id: uuid.UUID
    node_id: str | None
    kind: str
    severity: Severity
    payload: dict[str, Any]
    created_at: datetime
    status: AlertStatus
    acknowledged_at: datetime | None
    acknowledged_by: str | None
    resolved_at: datetime | None
    resolved_by: str | None
    deliveries: list[Delivery]


class AlertPage(BaseModel):
    items: list[Alert]
    next_cursor: str | None


class ApiKey(_Out):
    id: int
    name: str
    role: Role
    site: str | None = Field(None, description="a gateway key's site: the only one it may write for")
    key_prefix: str = Field(description="first characters of the key, to recognise it")
    created_at: datetime
    revoked_at: datetime | None


class ApiKeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=128, pattern=r"^[^\x00-\x1f\x7f]+$")
    role: Literal["viewer", "operator", "admin"]


class GatewayKeyCreate(BaseModel):
    """A key for one gateway reporting to this central site: it may only ingest, for its site only."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=128, pattern=r"^[^\x00-\x1f\x7f]+$")
    role: Literal["gateway"]
    site: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$", description="the only site it may write for")


AnyKeyCreate = Annotated[ApiKeyCreate | GatewayKeyCreate, Field(discriminator="role")]


class ApiKeyCreated(ApiKey):
    token: str = Field(description="the key itself: shown once, only its hash is stored")


class Liveness(BaseModel):
    status: str = "ok"


class Readiness(BaseModel):
    status: str = "ready"
    schema_revision: str
