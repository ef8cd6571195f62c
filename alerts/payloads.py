"""The alert payload: the JSON every sink is given, as typed models (a versioned external contract).

``PAYLOAD_SCHEMA`` is its version; receivers may rely on every field documented here
(docs/alerting.md publishes :func:`payload_json_schema`). A change that removes or retypes a
field, or changes what one means, is a new version; a new optional field is not (receivers
ignore what they do not know). An optional field that is not known is left out of the JSON
rather than sent as null (``omitted_when_none``), so adding one changes nothing for events
without it.
"""
from __future__ import annotations

import uuid
from datetime import datetime
from typing import Annotated, Any, ClassVar, Final, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    SerializerFunctionWrapHandler,
    TypeAdapter,
    WithJsonSchema,
    model_serializer,
)
from pydantic.json_schema import models_json_schema

from db.models import NodeState, Severity

PAYLOAD_SCHEMA: Final = 2
# 2: every alarm event says which alarm (``alarm``, ``alarm_id``) and every end why it ended
# (``ended_by``: recovery, re-baseline, decommissioning); an end no longer implies the node is
# ok (damage_cleared after a re-baseline says calibrating) or online (node_online ended by a
# decommissioning has online false).

# An instant as the payload has always carried it: ISO 8601 with its UTC offset (``+00:00``).
Instant = Annotated[
    datetime,
    PlainSerializer(lambda value: value.isoformat(), return_type=str),
    WithJsonSchema({"type": "string", "format": "date-time"}),
]


def _omitted_fields_not_nullable(schema: dict[str, Any], model: type[BaseModel]) -> None:
    """In the published schema, a field left out when unknown is optional and never null."""
    omitted: frozenset[str] = getattr(model, "omitted_when_none", frozenset())
    properties = schema.get("properties", {})
    for name in omitted:
        prop = properties.get(name)
        if prop is None:
            continue
        branches = [b for b in prop.pop("anyOf", []) if b != {"type": "null"}]
        if len(branches) == 1:
            prop.update(branches[0])
        elif branches:
            prop["anyOf"] = branches
        prop.pop("default", None)
    if "required" in schema:
        schema["required"] = [name for name in schema["required"] if name not in omitted]


class PayloadPart(BaseModel):
    """A part of a payload: fields in the order receivers have always seen them."""

    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        populate_by_name=True,
        json_schema_serialization_defaults_required=True,
        json_schema_extra=_omitted_fields_not_nullable,
    )
    omitted_when_none: ClassVar[frozenset[str]] = frozenset()

    # No return annotation: pydantic then keeps each model's own schema for serialization.
    @model_serializer(mode="wrap")
    def _leave_out_unknown_optionals(self, handler: SerializerFunctionWrapHandler):
        data = handler(self)
        for name in self.omitted_when_none:
            if data.get(name) is None:
                data.pop(name, None)
        return data


class Detection(PayloadPart):
    """The DI peak against the node's threshold (null while the threshold is being calibrated)."""

    peak_di: float
    threshold: float | None
    di_over_threshold: float | None = Field(description="peak_di / threshold, 4 decimals")


class Location(PayloadPart):
    """The estimated defect position, 0.1 mm / 0.1 degree: axial from the Tx ring, angle on the circumference;
    with its 90 % localization region when the detection has one (imaging/region.py)."""

    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"axial_half_mm", "circumferential_half_mm",
                                                             "localized"})

    axial_mm: float
    angle_deg: float
    axial_half_mm: float | None = Field(None, description="90 % region: half-width along the axis, mm")
    circumferential_half_mm: float | None = Field(None, description="90 % region: half-width round the pipe, mm")
    localized: bool | None = Field(None, description="false: the map does not resolve the position; the region "
                                   "spans what the evidence leaves open")


class Links(PayloadPart):
    """Where the operator API shows the node and the measurement (only those that apply)."""

    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"node", "measurement", "di_map_png"})

    node: str | None = None
    measurement: str | None = None
    di_map_png: str | None = None


class Receiver(PayloadPart):
    """One receiver (transducer channel) judged faulty: imaging/health.py's verdict."""

    rx_index: int
    rx_angle_deg: float | None
    kind: str = Field(description="no_signal, amplitude or timing")
    amplitude_ratio: float | None = Field(description="direct arrival, current / baseline")
    delay_s: float | None = Field(description="direct arrival shift against the median receiver")


class Decommissioning(PayloadPart):
    at: Instant
    by: str
    reason: str


class EndedBy(PayloadPart):
    """Why an alarm ended (docs/alerting.md, "Alarms and how they end")."""

    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"by", "reason", "baseline_id"})

    cause: Literal["recovery", "rebaseline", "decommissioning"] = Field(
        description="recovery: the node says the problem is gone; rebaseline: an operator set a new active "
        "baseline after the alarm was raised; decommissioning: an admin took the node out of service")
    by: str | None = Field(None, description="who set the baseline / decommissioned the node")
    reason: str | None = Field(None, description="their reason")
    baseline_id: int | None = Field(None, description="rebaseline: the baseline record that ended it")


AlarmId = Annotated[uuid.UUID, Field(description="the id of the event that first raised the alarm (an escalation "
                                                 "and the end keep it): one per alarm")]


class EventPayload(PayloadPart):
    """What every alert carries, whatever its kind."""

    schema_version: Literal[2] = Field(PAYLOAD_SCHEMA, alias="schema", description="the payload's version")
    event_id: uuid.UUID = Field(description="stable id of the fact (uuid5): receivers de-duplicate on it")
    kind: str
    node_id: str | None
    severity: Severity
    routing_severity: Severity = Field(description="the severity that chose the sinks (a clearing goes where "
                                                   "its alarm went)")
    occurred_at: Instant
    summary: str
    state: NodeState | None = Field(description="the node's state after the event")
    previous_state: NodeState | None
    online: bool | None
    measurement_id: int | None = None
    detection: Detection | None = None
    location: Location | None = None
    links: Links


class StateChangePayload(EventPayload):
    """The node's damage or blind alarm: raised (or escalated) or ended."""

    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"reason", "ended_by"})

    kind: Literal["damage_raised", "damage_cleared", "monitoring_blind", "monitoring_restored"]
    node_id: str
    reason: str | None = Field(None, description="monitoring_blind: why the imaging abstained")
    alarm: Literal["damage", "blind"]
    alarm_id: AlarmId
    ended_by: EndedBy | None = Field(None, description="damage_cleared, monitoring_restored: why the alarm ended")


class NodeOfflinePayload(EventPayload):
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"never_seen"})

    kind: Literal["node_offline"]
    node_id: str
    last_seen_at: Instant = Field(description="when the node last answered; never_seen: when the gateway started "
                                              "watching it (registered from its configuration)")
    offline_for_s: float
    alarm: Literal["offline"]
    alarm_id: AlarmId
    never_seen: Literal[True] | None = Field(None, description="true: the node has never answered (left out "
                                                               "otherwise)")


class NodeOnlinePayload(EventPayload):
    omitted_when_none: ClassVar[frozenset[str]] = frozenset({"first_seen"})

    kind: Literal["node_online"]
    node_id: str
    offline_event_id: uuid.UUID = Field(description="the node_offline event this one ends")
    offline_since: Instant = Field(description="that event's last_seen_at")
    offline_for_s: float
    alarm: Literal["offline"]
    alarm_id: AlarmId
    ended_by: EndedBy
    first_seen: Literal[True] | None = Field(None, description="true: the node answered for the first time (its "
                                                               "node_offline said never_seen; left out otherwise)")


class BaselineChangedPayload(EventPayload):
    kind: Literal["baseline_changed"]
    node_id: str
    baseline_id: int
    previous_measurement_id: int | None
    created_by: str
    reason: str


class NodeDecommissionedPayload(EventPayload):
    kind: Literal["node_decommissioned"]
    node_id: str
    decommissioned: Decommissioning


class NodeRecommissionedPayload(EventPayload):
    kind: Literal["node_recommissioned"]
    node_id: str
    decommissioned: None
    decommissioned_since: Instant


class NodeMisconfiguredPayload(EventPayload):
    """The node on the port is not the configured one, or does not run the configured settings."""

    kind: Literal["node_misconfigured"]
    node_id: str
    problems: list[str] = Field(description="each way the node differs from its configuration, in words")
    boot_id: int = Field(description="the node's boot in which it was found (docs/protocol.md 3.3)")


class SinkDisabledPayload(EventPayload):
    """A receiver answered 410 Gone; about no node (node_id, state and online are null)."""

    kind: Literal["sink_disabled"]
    sink: str
    endpoint_fingerprint: str
    status_code: int


class StorageUnavailablePayload(EventPayload):
    """The gateway could not write to its database for a while (disk full, I/O errors, read-only); about
    no node. Told when writes work again: what was acquired meanwhile was not stored."""

    kind: Literal["storage_unavailable"]
    since: Instant = Field(description="the first write that failed")
    until: Instant = Field(description="the first write that fitted again")
    failed_writes: int = Field(description="transactions refused meanwhile (measurements, health updates)")
    reason: str = Field(description="the first failure, e.g. StorageFull: SQLite: database or disk is full")


class ReceiverPayload(EventPayload):
    """About one receiver of a node."""

    node_id: str
    receiver: Receiver
    faulty_receivers: list[int] = Field(description="every receiver of the node with an open sensor_fault after it")
    consecutive_measurements: int


class SensorFaultPayload(ReceiverPayload):
    kind: Literal["sensor_fault"]
    alarm: Literal["sensor_fault"]
    alarm_id: AlarmId


class SensorFaultClearedPayload(ReceiverPayload):
    kind: Literal["sensor_fault_cleared"]
    raised_event_id: uuid.UUID = Field(description="the sensor_fault event this one ends")
    raised_measurement_id: int | None
    alarm: Literal["sensor_fault"]
    alarm_id: AlarmId
    ended_by: EndedBy


KIND_PAYLOADS: tuple[type[EventPayload], ...] = (
    StateChangePayload,
    NodeOfflinePayload,
    NodeOnlinePayload,
    BaselineChangedPayload,
    NodeDecommissionedPayload,
    NodeRecommissionedPayload,
    NodeMisconfiguredPayload,
    SinkDisabledPayload,
    StorageUnavailablePayload,
    SensorFaultPayload,
    SensorFaultClearedPayload,
)
AlertPayload = Annotated[
    StateChangePayload
    | NodeOfflinePayload
    | NodeOnlinePayload
    | BaselineChangedPayload
    | NodeDecommissionedPayload
    | NodeRecommissionedPayload
    | NodeMisconfiguredPayload
    | SinkDisabledPayload
    | StorageUnavailablePayload
    | SensorFaultPayload
    | SensorFaultClearedPayload,
    Field(discriminator="kind"),
]
ALERT_PAYLOAD: TypeAdapter[AlertPayload] = TypeAdapter(AlertPayload)


def payload_json(payload: EventPayload) -> dict[str, Any]:
    """The payload as the outbox stores it and every sink is given it."""
    return payload.model_dump(mode="json", by_alias=True)


def payload_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of every payload as receivers get it (docs/alerting.md).

    Each kind is the common ``EventPayload`` plus what it adds or narrows, and receivers may
    meet properties the schema does not list (a later optional field): no ``additionalProperties``.
    """
    published: tuple[type[EventPayload], ...] = (EventPayload, *KIND_PAYLOADS)
    models: list[tuple[type[BaseModel], Literal["serialization"]]] = [(m, "serialization") for m in published]
    _, generated = models_json_schema(models, by_alias=True, ref_template="#/$defs/{model}")
    defs = _published(generated["$defs"])
    base = defs["EventPayload"]
    for model in KIND_PAYLOADS:
        full = defs[model.__name__]
        added = {k: v for k, v in full["properties"].items() if base["properties"].get(k) != v}
        required = [k for k in full.get("required", []) if k not in base.get("required", [])]
        defs[model.__name__] = {
            "description": full.get("description", ""),
            "allOf": [{"$ref": "#/$defs/EventPayload"}, {"type": "object", "properties": added, "required": required}],
        }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"PipeSentry alert payload, schema {PAYLOAD_SCHEMA}",
        "oneOf": [{"$ref": f"#/$defs/{model.__name__}"} for model in KIND_PAYLOADS],
        "$defs": defs,
    }


def _published(node: Any) -> Any:
    """The generated schema without pydantic's derived titles and without closing objects to new fields."""
    if isinstance(node, dict):
        return {k: _published(v) for k, v in node.items() if k not in ("title", "additionalProperties")}
    if isinstance(node, list):
        return [_published(v) for v in node]
    return node
