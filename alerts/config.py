"""Alerting settings: where events go (sinks) and how hard delivery tries (timeouts, retries, backoff).

Part of the gateway config as the ``[alerting]`` table; each ``[[alerting.sinks]]`` entry is
one receiver, told apart by ``type`` (webhook | alertmanager | slack | mqtt).
"""
from __future__ import annotations

import base64
import binascii
import re
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

from db.models import Severity

SINK_NAME_PATTERN = r"^[A-Za-z0-9_.-]+$"
LABEL_NAME = re.compile(r"[a-zA-Z_][a-zA-Z0-9_]*")
RESERVED_LABELS = frozenset({"alertname", "node", "severity", "state", "rx_index", "kind"})
WEBHOOK_SECRET_PREFIX = "whsec_"
_SEVERITY_RANK = {Severity.INFO: 0, Severity.WARNING: 1, Severity.CRITICAL: 2}


# Durations beyond a week are typos (`backoff_cap_s = 1e300` would overflow the wait that uses it).
MAX_WAIT_S = 7 * 86_400.0


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # inf passes gt=0, then breaks a timer


class SinkSettings(_Section):
    """What every sink has: a name (stored in ``deliveries.sink``) and its delivery policy."""

    name: str = Field(min_length=1, max_length=64, pattern=SINK_NAME_PATTERN)
    timeout_s: float = Field(5.0, gt=0, le=120, description="whole-request timeout of one attempt")
    max_attempts: int = Field(10, ge=1, le=100, description="tries before a delivery is marked dead")
    backoff_base_s: float = Field(2.0, gt=0, le=MAX_WAIT_S, description="first retry waits up to this long (full jitter)")
    backoff_cap_s: float = Field(600.0, gt=0, le=MAX_WAIT_S, description="no retry waits longer (unless Retry-After says so)")
    retry_after_max_s: float = Field(3600.0, gt=0, le=MAX_WAIT_S, description="a receiver's Retry-After is honoured up to this")
    min_severity: Severity = Field(Severity.INFO, description="events routed below this severity skip the sink")

    @model_validator(mode="after")
    def _cap_not_below_base(self) -> SinkSettings:
        if self.backoff_cap_s < self.backoff_base_s:
            raise ValueError("backoff_cap_s must be >= backoff_base_s")
        return self

    def accepts(self, routing_severity: Severity) -> bool:
        return _SEVERITY_RANK[Severity(routing_severity)] >= _SEVERITY_RANK[self.min_severity]


class WebhookSinkSettings(SinkSettings):
    """A generic HTTPS receiver; requests are signed per Standard Webhooks (HMAC-SHA256)."""

    type: Literal["webhook"] = "webhook"
    url: str = Field(pattern=r"^https?://")
    secret: SecretStr = Field(description="whsec_<base64 key>, shared with the receiver")

    @field_validator("secret")
    @classmethod
    def _whsec(cls, value: SecretStr) -> SecretStr:
        webhook_key(value)
        return value


class AlertmanagerSinkSettings(SinkSettings):
    """Prometheus Alertmanager: active alerts are POSTed to ``{url}/api/v2/alerts`` and re-sent."""

    type: Literal["alertmanager"] = "alertmanager"
    url: str = Field(pattern=r"^https?://", description="Alertmanager base URL, e.g. http://127.0.0.1:9093")
    resend_interval_s: float = Field(60.0, gt=0, le=MAX_WAIT_S, description="active alerts are re-sent this often")
    labels: dict[str, str] = Field(
        default_factory=dict,
        description="added to every alert, e.g. {site = \"site-1\"} for a central Alertmanager's routes and "
        "inhibitions; cannot replace the alert's own labels",
    )

    @field_validator("labels")
    @classmethod
    def _label_names(cls, value: dict[str, str]) -> dict[str, str]:
        for name in value:
            if not LABEL_NAME.fullmatch(name):
                raise ValueError(f"{name!r} is not a Prometheus label name ([a-zA-Z_][a-zA-Z0-9_]*)")
            if name in RESERVED_LABELS:
                raise ValueError(f"{name!r} is set by PipeSentry itself ({', '.join(sorted(RESERVED_LABELS))})")
        return value


class SlackSinkSettings(SinkSettings):
    """A Slack-compatible incoming webhook (Slack, Mattermost, Rocket.Chat): one readable line."""

    type: Literal["slack"] = "slack"
    url: SecretStr = Field(description="the incoming-webhook URL (it is the credential)")

    @field_validator("url")
    @classmethod
    def _http_url(cls, value: SecretStr) -> SecretStr:
        if not value.get_secret_value().startswith(("http://", "https://")):
            raise ValueError("must be an http(s) URL")
        return value


class MqttSinkSettings(SinkSettings):
    """An MQTT broker: each node's current state retained on ``{topic_prefix}/{node_id}/state``, its events
    on ``.../events``, the gateway's status with a last will on ``{gateway_topic}/status``."""

    type: Literal["mqtt"] = "mqtt"
    host: str = Field(min_length=1)
    port: int = Field(1883, ge=1, le=65535)
    username: str | None = None
    password: SecretStr | None = None
    tls: bool = False
    topic_prefix: str = Field("pipesentry/nodes", min_length=1, pattern=r"^[^#+]+$",
                              description="{prefix}/{node}/state (retained), /events, /receivers/{rx}")
    gateway_topic: str = Field(
        "pipesentry/gateway", min_length=1, pattern=r"^[^#+]+$",
        description="{topic}/status (retained, with the last will) and {topic}/events; give each gateway "
        "sharing a broker its own, e.g. pipesentry/gateways/site-12",
    )
    state_interval_s: float = Field(5.0, gt=0, le=3600, description="how often node states are checked for changes")
    keepalive_s: int = Field(60, ge=5, le=3600)


AnySinkSettings = Annotated[
    WebhookSinkSettings | AlertmanagerSinkSettings | SlackSinkSettings | MqttSinkSettings,
    Field(discriminator="type"),
]


class AlertingSettings(_Section):
    """The ``[alerting]`` table of the gateway config."""

    api_base_url: str = Field(
        "http://127.0.0.1:8000", pattern=r"^https?://", description="links in alerts point here"
    )
    offline_after_s: float = Field(600.0, gt=0, le=MAX_WAIT_S, description="a node unseen this long raises node_offline")
    poll_interval_s: float = Field(1.0, gt=0, le=60, description="how often an idle sink looks at the outbox")
    sensor_fault_count: int = Field(
        2, ge=1, le=100,
        description="a receiver faulty in this many consecutive measurements raises sensor_fault; "
        "healthy in as many clears it",
    )
    sinks: list[AnySinkSettings] = Field(default_factory=list)

    @field_validator("api_base_url")
    @classmethod
    def _no_trailing_slash(cls, value: str) -> str:
        return value.rstrip("/")

    @model_validator(mode="after")
    def _unique_sink_names(self) -> AlertingSettings:
        names = [s.name for s in self.sinks]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ValueError(f"sink names must be unique, repeated: {', '.join(repeated)}")
        return self

    def sink_names_for(self, routing_severity: Severity) -> tuple[str, ...]:
        """The sinks an event routed at this severity goes to (in config order)."""
        return tuple(s.name for s in self.sinks if s.accepts(routing_severity))

    def sink(self, name: str) -> AnySinkSettings:
        for s in self.sinks:
            if s.name == name:
                return s
        raise KeyError(name)


def webhook_key(secret: SecretStr | str) -> bytes:
    """The HMAC key of a ``whsec_<base64>`` secret; ValueError if it is not one."""
    text = secret.get_secret_value() if isinstance(secret, SecretStr) else secret
    if not text.startswith(WEBHOOK_SECRET_PREFIX):
        raise ValueError(f"webhook secret must start with {WEBHOOK_SECRET_PREFIX!r}")
    try:
        key = base64.b64decode(text[len(WEBHOOK_SECRET_PREFIX):], validate=True)
    except (binascii.Error, ValueError):
        raise ValueError("webhook secret is not valid base64 after 'whsec_'") from None
    if not 24 <= len(key) <= 64:
        raise ValueError(f"webhook secret key must be 24 to 64 bytes, got {len(key)}")
    return key


def sink_secrets(sink: AnySinkSettings) -> list[str]:
    """What of a sink's settings is a credential: never to be logged, stored in an error or shown.

    A Slack webhook's URL and its path, webhook secrets, MQTT passwords, and the password and
    query of any URL (``https://user:pass@host/?token=...``).
    """
    secrets: list[str] = []
    url: str | None = None
    if isinstance(sink, SlackSinkSettings):
        url = sink.url.get_secret_value()
        secrets += [url, urlsplit(url).path]
    elif isinstance(sink, WebhookSinkSettings):
        url = sink.url
        secrets.append(sink.secret.get_secret_value())
    elif isinstance(sink, AlertmanagerSinkSettings):
        url = sink.url
    elif isinstance(sink, MqttSinkSettings) and sink.password is not None:
        secrets.append(sink.password.get_secret_value())
    if url is not None:
        parts = urlsplit(url)
        secrets += [p for p in (parts.password, parts.query) if p]
    return secrets
