"""The uplink's wire contract: one ``IngestBatch`` a gateway POSTs to the centre, and the answer.

Pure pydantic v2 models (bottom layer: imports nothing of ours). The gateway serialises its
database rows into these; the centre validates a whole batch before it writes any of it.

Rules the models state and check:

* every record carries a ``uid`` made at the edge, ``<gateway_id>/<kind>/<local id>``
  (:func:`record_uid`), the same on every retry, so a replayed batch duplicates nothing: the
  centre stores a uid once and counts a second sight as a duplicate. A uid must start with its
  batch's gateway and its record's kind (a gateway cannot write under another's name).
* records refer to each other by uid (a detection to its measurement, a baseline to its
  measurement, ...); a reference must name a record earlier in the same batch or one the centre
  already holds. The gateway therefore sends in its own order: node, then per node its
  measurements with their maps, baselines, detections, state changes and alert events.
* ``node`` records are the node's latest view, applied as an update: the newest by
  (``revision``, ``last_seen_at``) wins (:func:`node_record_is_stale`; the gateway raises a
  node's revision at every change of its record beyond its health, so an admin's change wins
  over an older record with the same ``last_seen_at``). Every other kind is immutable once
  stored, with two exceptions: a measurement stored without its traces takes them from a later
  record of the same uid that carries them (traces on demand, :func:`resent_measurement`), and
  a baseline takes its deactivation (``active``, ``deactivated_at``) from a later record of the
  same uid (:func:`resent_baseline`); nothing else of either changes.
* traces and map pixels travel as the gateway stores them (``shuffle-zlib-v1`` compressed
  bytes, base64), with their SHA-256, which the centre checks; a measurement's traces may be
  omitted (``data`` null) when the gateway's uplink policy sends no traces for it.
* traces on demand: the gateway polls ``TRACE_REQUESTS_PATH`` for the centre's requests for
  traces it did not send (:class:`TraceRequests`), queues each measurement again with its
  traces if it still holds them, and answers ``held`` or ``pruned`` (:class:`TraceAnswers`). A
  re-sent record the centre refuses is refused as any record is (the 422/403/409 names it); the
  centre itself ends the request ``refused`` with that refusal, so nothing more travels for it.
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import uuid
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, Final, Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator, model_validator

CONTRACT_VERSION: Final = 1
INGEST_PATH = "/api/v1/ingest/batches"
TRACE_REQUESTS_PATH = "/api/v1/ingest/trace-requests"  # GET ?gateway_id=: the requests to answer
TRACE_ANSWERS_PATH = "/api/v1/ingest/trace-requests/answers"  # POST TraceAnswers
MAX_TRACE_REQUESTS = 100  # requests in one answer of TRACE_REQUESTS_PATH, answers in one TraceAnswers
MAX_RECORDS_PER_BATCH = 500
# The request body after any gzip Content-Encoding is undone; the compressed body is bounded by it too.
# ~100 measurements with traces (about 75 kB of base64 each for 8 channels x 12,000 samples).
MAX_BODY_BYTES = 8 * 1024 * 1024
CODEC_SHUFFLE_ZLIB_V1: Final = "shuffle-zlib-v1"
PROBLEM_BAD_RECORD = "urn:pipesentry:problem:ingest-bad-record"

_NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"  # a gateway id, a site, a node id: safe in a uid and a URL
GatewayId = Annotated[str, Field(pattern=_NAME, description="the gateway's id, unique in the fleet")]
SiteName = Annotated[str, Field(pattern=_NAME, description="the site the gateway serves")]
NodeId = Annotated[str, Field(pattern=_NAME, max_length=64)]
Uid = Annotated[str, Field(min_length=5, max_length=200, description="<gateway_id>/<kind>/<local id>")]
NodeStateName = Literal["commissioning", "calibrating", "ok", "suspected", "damage", "no_valid_baseline"]
RecordKind = Literal["node", "measurement", "baseline", "detection", "state_change", "alert_event"]
RECORD_KINDS: tuple[RecordKind, ...] = ("node", "measurement", "baseline", "detection", "state_change", "alert_event")


def record_uid(gateway_id: str, kind: RecordKind, local_id: object) -> str:
    """The stable uid of one record: ``<gateway_id>/<kind>/<local id>`` (the local id as the gateway keys it)."""
    return f"{gateway_id}/{kind}/{local_id}"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Blob(_Model):
    """Stored bytes of an array as the gateway keeps them; ``data`` is their base64, or null when not sent."""

    codec: Literal["shuffle-zlib-v1"] = CODEC_SHUFFLE_ZLIB_V1
    dtype: Literal["<i2", "<f4"]
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    nbytes: int = Field(ge=0, description="length of the stored (compressed) bytes, as the gateway's row keeps it")
    data: str | None = Field(default=None, description="standard base64 of the stored (compressed) bytes")

    @field_validator("data")
    @classmethod
    def _base64(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                base64.b64decode(value, validate=True)
            except binascii.Error as exc:
                raise ValueError(f"data is not standard base64: {exc}") from None
        return value

    @model_validator(mode="after")
    def _checksum(self) -> Blob:
        if self.data is not None:
            stored = self.raw()
            if len(stored) != self.nbytes:
                raise ValueError(f"data is {len(stored)} bytes, nbytes says {self.nbytes}")
            if hashlib.sha256(stored).hexdigest() != self.sha256:
                raise ValueError("data does not match its sha256")
        return self

    def raw(self) -> bytes:
        """The stored bytes (``b""`` only for an empty blob); raises ValueError when ``data`` was not sent."""
        if self.data is None:
            raise ValueError("the blob's data was not sent")
        return base64.b64decode(self.data)

    @classmethod
    def of(cls, stored: bytes | None, *, dtype: Literal["<i2", "<f4"], sha256: str, nbytes: int) -> Blob:
        """The wire form of stored bytes (``stored`` None: described by checksum and length, not sent)."""
        data = None if stored is None else base64.b64encode(stored).decode("ascii")
        return cls(dtype=dtype, sha256=sha256, nbytes=nbytes, data=data)


class NodeRecord(_Model):
    """A node's identity, geometry and latest state (an update: the newest ``last_seen_at`` wins)."""

    kind: Literal["node"] = "node"
    uid: Uid
    node_id: NodeId
    firmware: str = Field(max_length=64)
    protocol_version: int
    n_channels: int = Field(ge=1)
    fs_hz: float = Field(gt=0)
    geometry: dict[str, Any] = Field(description="ring angles, tx_rx_distance_mm, circumference_mm, ...")
    first_seen_at: AwareDatetime
    last_seen_at: AwareDatetime
    online: bool
    state: NodeStateName
    latest_di_peak: float | None = None
    latest_threshold: float | None = None
    label: str | None = Field(default=None, max_length=128)
    location: str | None = Field(default=None, max_length=256)
    decommissioned_at: AwareDatetime | None = None
    decommissioned_by: str | None = Field(default=None, max_length=128)
    decommission_reason: str | None = Field(default=None, max_length=2000)
    revision: int = Field(
        default=0, ge=0,
        description="the gateway's count of changes to this record beyond the node's health (INFO, details, "
                    "(re)commissioning); 0 from a gateway that counts none",
    )


def node_record_is_stale(
    held_revision: int | None, held_last_seen_at: datetime | None, record: NodeRecord,
) -> bool:
    """Whether a node record is older than the centre's view of the node (pure): ordered by
    (``revision``, ``last_seen_at``), both of which only grow at the gateway; a view the centre got
    from no record, or from a gateway that sends no revision, counts as revision 0."""
    if held_last_seen_at is None:
        return False
    return (record.revision, record.last_seen_at) < (held_revision or 0, held_last_seen_at)


class MeasurementSettings(_Model):
    """How the acquisition was made (the measurement row's settings columns)."""

    temperature_c: float | None = None
    averaging: int
    fs_hz: float = Field(gt=0)
    t0_s: float
    n_channels: int = Field(ge=1)
    n_samples: int = Field(ge=1)
    volts_per_code: float
    excitation_hz: float
    cycles: int


class DiMapRecord(_Model):
    """A damage-index map of the measurement it travels in (not a record of its own)."""

    source: Literal["node", "gateway"]
    method: str = Field(max_length=64)
    grid: dict[str, Any]
    baseline_measurement_uid: Uid | None = None
    pixels: Blob
    peak_di: float
    created_at: AwareDatetime


class MeasurementRecord(_Model):
    kind: Literal["measurement"] = "measurement"
    uid: Uid
    node_id: NodeId
    measurement_kind: Literal["baseline", "monitor"]
    acquired_at: AwareDatetime
    node_measurement_id: int
    boot_id: int | None = None
    settings: MeasurementSettings
    velocity_m_s: float | None = None
    wall_mm: float | None = None
    traces: Blob = Field(description="the raw ADC codes; data null when the gateway sends no traces for it")
    di_maps: list[DiMapRecord] = Field(default_factory=list)


class BaselineRecord(_Model):
    kind: Literal["baseline"] = "baseline"
    uid: Uid
    node_id: NodeId
    measurement_uid: Uid
    created_by: str = Field(max_length=128)
    created_at: AwareDatetime
    reason: str
    active: bool
    deactivated_at: AwareDatetime | None = None


@dataclass(frozen=True)
class BaselineView:
    """A baseline record's fields, as sent or as the centre holds them (its measurement by uid)."""

    node_id: str
    measurement_uid: str
    created_by: str
    created_at: datetime
    reason: str
    active: bool
    deactivated_at: datetime | None

    @classmethod
    def of(cls, record: BaselineRecord) -> BaselineView:
        return cls(record.node_id, record.measurement_uid, record.created_by, record.created_at, record.reason,
                   record.active, record.deactivated_at)


ResentBaseline = Literal["deactivate", "duplicate", "stale"]


def resent_baseline(stored: BaselineView, sent: BaselineView) -> ResentBaseline:
    """A baseline record whose uid the centre holds already (pure).

    A baseline only ever goes from active to inactive at the gateway (setting another baseline
    makes a new record), so: ``deactivate`` when the stored one is active and the record says it
    was deactivated (the centre takes ``active`` and ``deactivated_at``); ``duplicate`` when they
    agree, or both are inactive (the centre may have deactivated it itself when the newer active
    baseline arrived first: it keeps its time); ``stale`` when the record says active for a
    baseline the centre holds inactive (an older view, ignored). Raises ValueError when anything
    else differs (node, measurement, who, when, why): those never change.
    """
    fixed = ("node_id", "measurement_uid", "created_by", "created_at", "reason")
    changed = [name for name in fixed if getattr(stored, name) != getattr(sent, name)]
    if changed:
        raise ValueError(f"a stored baseline does not change; this record changes its {', '.join(changed)}")
    if stored.active and not sent.active:
        return "deactivate"
    if not stored.active and sent.active:
        return "stale"
    return "duplicate"


class DetectionRecord(_Model):
    kind: Literal["detection"] = "detection"
    uid: Uid
    node_id: NodeId
    measurement_uid: Uid
    peak_di: float | None = None
    threshold: float | None = None
    axial_mm: float | None = None
    angle_deg: float | None = None
    state: NodeStateName
    confidence: float | None = None
    method: str | None = Field(default=None, max_length=32)
    defects: list[Any] | None = None
    sensor_faults: list[Any] | None = None
    baseline_measurement_uid: Uid | None = None
    stretch: float | None = None
    abstain_reason: str | None = None
    created_at: AwareDatetime


class StateChangeRecord(_Model):
    kind: Literal["state_change"] = "state_change"
    uid: Uid
    node_id: NodeId
    measurement_uid: Uid | None = None
    from_state: NodeStateName
    to_state: NodeStateName
    at: AwareDatetime


class AlertEventRecord(_Model):
    """An alert event from the gateway's outbox (its id is the edge's event id)."""

    kind: Literal["alert_event"] = "alert_event"
    uid: Uid
    event_id: uuid.UUID
    node_id: NodeId | None = None
    event_kind: str = Field(max_length=64, description="the event's kind, e.g. damage_detected")
    severity: Literal["info", "warning", "critical"]
    payload: dict[str, Any]
    created_at: AwareDatetime
    deliver_centrally: bool = Field(
        default=False,
        description="true: the gateway leaves this alert to the centre's sinks (it does not send it itself)",
    )


Record = Annotated[
    NodeRecord | MeasurementRecord | BaselineRecord | DetectionRecord | StateChangeRecord | AlertEventRecord,
    Field(discriminator="kind"),
]


class IngestBatch(_Model):
    """What a gateway POSTs to ``INGEST_PATH`` (JSON, optionally ``Content-Encoding: gzip``)."""

    contract_version: Literal[1] = CONTRACT_VERSION
    gateway_id: GatewayId
    site: SiteName
    batch_id: uuid.UUID = Field(description="made by the edge; a retry sends the same batch again")
    records: list[Record] = Field(min_length=1, max_length=MAX_RECORDS_PER_BATCH)

    @model_validator(mode="after")
    def _uids_are_this_gateways(self) -> IngestBatch:
        seen: set[str] = set()
        for index, record in enumerate(self.records):
            prefix = f"{self.gateway_id}/{record.kind}/"
            if not record.uid.startswith(prefix) or len(record.uid) == len(prefix):
                raise ValueError(f"record {index}: uid {record.uid!r} must be {prefix}<local id>")
            if record.uid in seen:
                raise ValueError(f"record {index}: uid {record.uid!r} appears twice in the batch")
            seen.add(record.uid)
        return self


class IngestResult(_Model):
    """The centre's answer to a stored batch (200): nothing of it was half-written."""

    batch_id: uuid.UUID
    accepted: int = Field(description="records stored now (nodes: created or updated)")
    duplicates: int = Field(description="records the centre already held (a retried batch: all of them)")
    stale: int = Field(default=0, description="node records older than the centre's view of the node, and "
                                              "baseline records re-activating one it holds deactivated: ignored")


class BadRecord(_Model):
    """The ``bad_record`` member of a 422/403/409 problem+json refusing a batch: which record, and why."""

    index: int | None = Field(description="position in records; null when the batch itself is malformed")
    uid: str | None = None
    kind: str | None = None
    error: str


# ------------------------------------------------------------------ traces on demand
ResentOutcome = Literal["add_traces", "duplicate"]


@dataclass(frozen=True)
class StoredTraces:
    """What the centre holds of a stored measurement's traces: their description, and whether the bytes are here."""

    here: bool
    codec: str
    dtype: str
    sha256: str
    nbytes: int


def resent_measurement(stored: StoredTraces, record: MeasurementRecord) -> ResentOutcome:
    """A measurement record whose uid the centre holds already (pure): ``add_traces`` when it brings
    the traces the stored record lacks, else ``duplicate`` (a replay: nothing changes).

    Raises ValueError when it brings traces that are not the stored measurement's (another
    checksum, length, dtype or codec): a stored measurement is immutable, its traces included.
    """
    traces = record.traces
    if traces.data is None:
        return "duplicate"
    sent = (traces.codec, traces.dtype, traces.sha256, traces.nbytes)
    if sent != (stored.codec, stored.dtype, stored.sha256, stored.nbytes):
        raise ValueError(
            f"traces (sha256 {traces.sha256[:12]}..., {traces.nbytes} bytes) are not the stored measurement's "
            f"(sha256 {stored.sha256[:12]}..., {stored.nbytes} bytes): a stored measurement does not change"
        )
    return "duplicate" if stored.here else "add_traces"


class TraceRequest(_Model):
    """A central operator asks for the raw traces of one of the gateway's measurements."""

    request_id: int
    measurement_uid: Uid
    requested_at: AwareDatetime


class TraceRequests(_Model):
    """The answer to ``GET TRACE_REQUESTS_PATH?gateway_id=``: the requests not answered yet, oldest first."""

    gateway_id: GatewayId
    items: list[TraceRequest] = Field(max_length=MAX_TRACE_REQUESTS)


class TraceAnswer(_Model):
    """``held``: the gateway holds the traces and has queued the measurement with them;
    ``pruned``: it no longer holds them (retention removed them, or it never had the measurement)."""

    request_id: int
    measurement_uid: Uid
    answer: Literal["held", "pruned"]


class TraceAnswers(_Model):
    """What a gateway POSTs to ``TRACE_ANSWERS_PATH``: its answers to the requests it was given."""

    contract_version: Literal[1] = CONTRACT_VERSION
    gateway_id: GatewayId
    site: SiteName
    answers: list[TraceAnswer] = Field(min_length=1, max_length=MAX_TRACE_REQUESTS)

    @model_validator(mode="after")
    def _uids_are_this_gateways(self) -> TraceAnswers:
        prefix = f"{self.gateway_id}/measurement/"
        for index, answer in enumerate(self.answers):
            if not answer.measurement_uid.startswith(prefix) or len(answer.measurement_uid) == len(prefix):
                raise ValueError(f"answer {index}: uid {answer.measurement_uid!r} must be {prefix}<local id>")
        return self


class TraceAnswersResult(_Model):
    updated: int = Field(description="requests the answers moved on (a repeated or late answer changes nothing)")
