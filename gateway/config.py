"""The gateway's settings: one TOML file, validated, overridable by PIPESENTRY_* environment variables.

Environment variables use ``__`` between levels, e.g. ``PIPESENTRY_DATABASE__URL`` or
``PIPESENTRY_LOGGING__JSON=true``. A config error names the offending key and the daemon does
not start half-configured. Validation is everything a start needs and opens nothing (no port,
no database): ``pipesentry gateway --check`` is exactly :func:`load_settings`.
"""
from __future__ import annotations

import importlib.util
import os
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, SettingsError

from alerts.config import AlertingSettings
from db.urls import DatabaseUrlError, check_database_url
from imaging.compensation import DEFAULT_MAX_COMPENSATED_STRETCH
from uplink.contract import MAX_BODY_BYTES, MAX_RECORDS_PER_BATCH

# Upper bounds of the durations: far beyond any sensible setting, and far below what a timer can
# wait (threading's TIMEOUT_MAX): `interval_s = 1e300` is a typo, not a schedule.
DAY_S = 86_400.0
MAX_INTERVAL_S = 7 * DAY_S
MAX_TIMEOUT_S = 600.0
# pyserial URL schemes it has a handler for (serial.urlhandler.protocol_<scheme>); a path has none.
_PYSERIAL_HANDLERS = "serial.urlhandler.protocol_"


class ConfigError(ValueError):
    """The configuration is invalid; the message names the offending key(s)."""


class _Section(BaseModel):
    # No inf or nan anywhere: a duration of inf passes `gt=0` and then kills the thread that waits on it.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class DatabaseSettings(_Section):
    url: str = Field(
        "sqlite:///pipesentry.db",
        description="sqlite:///relative.db, sqlite:////absolute.db or postgresql+psycopg://user@host/db",
    )
    integrity_check_every_s: float = Field(
        DAY_S, gt=0, le=MAX_INTERVAL_S, description="SQLite: PRAGMA quick_check at every start and this often; "
        "a damaged database stops the gateway (exit 2) before anything more is written into it",
    )

    @field_validator("url")
    @classmethod
    def _usable_url(cls, value: str) -> str:
        try:
            check_database_url(value, writable=True)  # the gateway creates the file and its WAL files
        except DatabaseUrlError as exc:
            raise ValueError(str(exc)) from None
        return value


class RetentionSettings(_Section):
    raw_traces_days: float = Field(365.0, gt=0, le=36_500, description="raw traces older than this are pruned")
    prune_batch: int = Field(50, ge=1, le=10_000, description="measurements pruned per transaction")
    prune_every_s: float = Field(3600.0, gt=0, le=MAX_INTERVAL_S)


class LoggingSettings(_Section):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    json_lines: bool = Field(False, alias="json", description="one JSON object per log line")


class MetricsSettings(_Section):
    """The gateway's own Prometheus metrics (cycles, retries, delivery attempts; docs/gateway.md)."""

    enabled: bool = True
    host: str = Field("127.0.0.1", min_length=1, description="listen address; 0.0.0.0 to be scraped from elsewhere")
    port: int = Field(9646, ge=0, le=65535, description="0: any free port (the log says which)")


class UplinkSettings(_Section):
    """Store-and-forward to a central PipeSentry (docs/gateway.md, "Uplink"): off unless ``[uplink]`` is set."""

    url: str = Field(pattern=r"^https?://[^/?#\s]+", description="the central API's base URL, e.g. https://central.example")
    key: SecretStr | None = Field(None, description="the gateway's API key (role gateway); or key_file")
    key_file: Path | None = Field(None, description="a file holding the key (first line), readable by the gateway")
    gateway_id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$",
                            description="this gateway's name at the centre: the first part of every record's uid")
    site: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$",
                      description="the site its key may write")
    send: Literal["everything", "flagged_traces"] = Field(
        "everything", description="flagged_traces: every record, but raw traces only of flagged measurements, "
        "baselines and those the centre asks for")
    batch_records: int = Field(50, ge=1, le=MAX_RECORDS_PER_BATCH, description="records per batch at most")
    batch_bytes: int = Field(4_000_000, ge=10_000, le=MAX_BODY_BYTES,
                             description="request body (before gzip) per batch at most; a bigger record goes alone")
    timeout_s: float = Field(30.0, gt=0, le=MAX_TIMEOUT_S, description="one request: connect, send, answer")
    idle_s: float = Field(2.0, gt=0, le=3600, description="how often an empty queue is looked at")
    requests_every_s: float = Field(60.0, gt=0, le=DAY_S,
                                    description="how often the centre is asked for its trace requests (traces on "
                                    "demand: the gateway only talks outbound)")
    backoff_base_s: float = Field(1.0, gt=0, le=3600, description="first wait after a failed batch (full jitter)")
    backoff_cap_s: float = Field(300.0, gt=0, le=DAY_S, description="no wait is longer (unless Retry-After says so)")
    retry_after_max_s: float = Field(3600.0, gt=0, le=DAY_S, description="the centre's Retry-After honoured up to this")
    refusals_max: int = Field(3, ge=1, le=100,
                              description="a record the centre refuses this often is set aside (kept, not sent)")
    ready_lag_s: float = Field(3600.0, gt=0, le=MAX_INTERVAL_S,
                               description="readiness fails while the oldest unsent record is older than this")

    @model_validator(mode="after")
    def _one_key(self) -> UplinkSettings:
        if (self.key is None) == (self.key_file is None):
            raise ValueError("set exactly one of 'key' and 'key_file'")
        if self.key is not None and not self.key.get_secret_value().strip():
            raise ValueError("key is empty")
        if self.key_file is not None:
            self.read_key()  # --check finds an unreadable or empty key file, not the first upload
        if self.backoff_cap_s < self.backoff_base_s:
            raise ValueError(f"backoff_cap_s ({self.backoff_cap_s}) is below backoff_base_s ({self.backoff_base_s})")
        return self

    def read_key(self) -> str:
        """The key: ``key``, or the first line of ``key_file``; ValueError naming the file otherwise."""
        if self.key is not None:
            return self.key.get_secret_value().strip()
        assert self.key_file is not None
        try:
            text = self.key_file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ValueError(f"key_file {self.key_file}: cannot read it ({reason})") from None
        key = text.strip().partition("\n")[0].strip()
        if not key:
            raise ValueError(f"key_file {self.key_file}: is empty")
        return key


class ThresholdSettings(_Section):
    """Damage flagging on the DI peak (normalised DI, see docs/imaging.md)."""

    mode: Literal["absolute", "calibrated"] = "calibrated"
    absolute: float | None = Field(None, gt=0, description="threshold when mode = absolute")
    calibration_count: int = Field(
        10, ge=5, le=1000, description="K baseline-condition measurements for mode = calibrated (fewer cannot bound a rare tail)"
    )
    false_alarm_rate: float = Field(1e-3, gt=0, lt=0.5, description="per measurement, for the calibrated bound")
    hysteresis_count: int = Field(3, ge=1, le=100, description="M consecutive exceedances to flag damage, M below to clear")
    floor: float | None = Field(
        None,
        ge=0,
        description="a calibrated threshold is never below this; None: the imaging method's documented default "
        "(set from a +-2 degC campaign), 0: no floor",
    )

    @model_validator(mode="after")
    def _absolute_needs_a_value(self) -> ThresholdSettings:
        if self.mode == "absolute" and self.absolute is None:
            raise ValueError("mode = 'absolute' needs 'absolute' set to the threshold value")
        return self


class ImagingSettings(_Section):
    """How the gateway images a node's measurements (docs/imaging.md)."""

    method: Literal["multipath", "paper"] = Field("multipath", description="paper = Algorithm 1 as published")
    feature: Literal["analytic", "envelope", "squared"] = "analytic"
    compensate: bool = Field(True, description="temperature compensation: optimal baseline selection + stretch")
    max_residual: float | None = Field(
        None, gt=0, description="relative residual after compensation above which the record is a wrong reference "
        "unless located defects explain it (a strong defect: docs/imaging.md); None: the default 0.05"
    )
    max_defects: int = Field(3, ge=1, le=16)
    max_compensated_stretch: float = Field(
        DEFAULT_MAX_COMPENSATED_STRETCH,
        gt=0,
        le=0.005,
        description="abstain (no_valid_baseline) when even the closest library baseline needs more time-stretch "
        "than this (0.0015: about 15 degC in steel); the node then needs a baseline at that temperature",
    )
    modal_orders: Literal["auto", "off"] | Annotated[int, Field(ge=0, le=8)] = Field(
        "off",
        description="remove the lowest circumferential orders across the ring before imaging (imaging/modal.py): "
        "'auto' (0-1 for 16 receivers, 0 for 8), 0..8, or 'off'; for rings that leak other modes strongly",
    )
    thermometer: bool = Field(
        True, description="where a strong change (beyond max_residual's default 5 %) bought a stretch the records' "
        "temperatures disagree with, image with theirs (docs/imaging.md); off for a node whose sensor is not trusted",
    )
    library_size: int = Field(24, ge=1, le=256, description="baselines kept in the node's OBS library")
    library_temperature_step_c: float = Field(
        2.0, ge=0, le=100, description="a healthy measurement this far (degC) from every library baseline joins it; 0: off"
    )
    library_growth_days: float = Field(
        30.0, gt=0, le=36_500, description="the library grows only this long after the active baseline was set"
    )


class GeometryOverride(_Section):
    """Geometry that overrides what the node reports in INFO (e.g. a node configured wrongly)."""

    rx_angles_deg: list[float] | None = None
    tx_angles_deg: list[float] | None = None
    tx_rx_distance_mm: float | None = Field(None, gt=0)
    circumference_mm: float | None = Field(None, gt=0)
    velocity_m_s: float | None = Field(None, gt=0)
    pipe_length_mm: float | None = Field(None, gt=0)
    tx_axial_mm: float | None = Field(None, ge=0)
    wall_mm: float | None = Field(None, gt=0, description="pipe wall, for the mid-wall circumference waves travel")


class NodeSettings(_Section):
    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    url: str = Field(min_length=1, description="pyserial URL: /dev/ttyUSB0, socket://host:port, loop://")
    baud: int = Field(230400, gt=0, le=20_000_000)
    interval_s: float = Field(60.0, gt=0, le=MAX_INTERVAL_S, description="time between measurement cycles")
    # The host timeouts docs/protocol.md (section 3.5) tells an integrator to set:
    timeout_s: float = Field(2.0, gt=0, le=MAX_TIMEOUT_S, description="reply timeout per command, and the longest gap in a bulk reply")
    retries: int = Field(3, ge=0, le=20, description="resends after a timeout or ERROR BUSY (same request id)")
    backoff_s: float = Field(0.05, gt=0, le=60, description="first wait before a resend; doubles per resend")
    backoff_max_s: float = Field(2.0, gt=0, le=600, description="cap of the wait before a resend")
    shot_period_s: float = Field(
        0.01, gt=0, le=10, description="ACQUIRE waits timeout_s + averaging x shot_period_s: the node's pulse period"
    )
    compute_timeout_s: float = Field(
        60.0, gt=0, le=86400, description="COMPUTE_DI's wait: as long as the node's on-board DI may take"
    )
    transfer_rounds: int = Field(4, ge=0, le=64, description="chunk re-request rounds per bulk transfer")
    read_node_di: bool = Field(True, description="also read the node's own on-board DI map")
    commissioning_count: int = Field(1, ge=1, le=100, description="first N measurements become baselines")
    excitation_hz: float = Field(85e3, ge=1e3, le=1e6, description="tone-burst centre frequency sent in CONFIGURE")
    cycles: int = Field(5, ge=1, le=50)
    averaging: int = Field(10, ge=1, le=10000, description="shots averaged per measurement (the paper: 10)")
    n_samples: int = Field(6000, ge=16, le=1_000_000, description="record length per channel")
    geometry: GeometryOverride = GeometryOverride()
    imaging: ImagingSettings = ImagingSettings()
    threshold: ThresholdSettings = ThresholdSettings()

    @model_validator(mode="after")
    def _backoff_in_order(self) -> NodeSettings:
        if self.backoff_max_s < self.backoff_s:
            raise ValueError(f"backoff_max_s ({self.backoff_max_s}) is below backoff_s ({self.backoff_s})")
        return self

    def client_options(self) -> dict[str, float | int]:
        """The NodeClient keyword arguments these settings give (docs/protocol.md, section 3.5)."""
        return {
            "baudrate": self.baud, "timeout_s": self.timeout_s, "retries": self.retries,
            "backoff_s": self.backoff_s, "backoff_max_s": self.backoff_max_s, "shot_period_s": self.shot_period_s,
            "compute_timeout_s": self.compute_timeout_s, "transfer_rounds": self.transfer_rounds,
        }

    def worst_cycle_s(self) -> float:
        """The longest a cycle can take before every command has given up: the wait between cycles,
        ~60 replies and gaps of a cycle with a reconfiguration and two bulk transfers, and the
        acquisition's and on-board DI's own waits, each resent ``retries`` times."""
        per_attempt_s = 60 * self.timeout_s + self.averaging * self.shot_period_s + self.compute_timeout_s
        resends_s = self.retries * self.backoff_max_s
        return self.interval_s + (self.retries + 1) * per_attempt_s + resends_s

    @field_validator("url")
    @classmethod
    def _pyserial_can_open(cls, value: str) -> str:
        scheme, sep, _ = value.partition("://")
        if sep and importlib.util.find_spec(_PYSERIAL_HANDLERS + scheme.lower()) is None:
            raise ValueError(f"pyserial has no {scheme!r}:// handler (a device path, socket://host:port, "
                             "rfc2217://host:port, loop://, ...)")
        return value

    @property
    def port_key(self) -> str:
        """What identifies the port: ``/dev/ttyS1``, ``//dev/ttyS1`` and ``/dev/./ttyS1`` are one port,
        and so are a symlink (``/dev/serial/by-id/...``) and the device it points to, when it exists."""
        scheme, sep, rest = self.url.partition("://")
        if sep:
            return f"{scheme.lower()}://{rest.lower()}"
        return os.path.realpath(self.url)


class GatewaySettings(BaseSettings):
    """Everything the gateway daemon needs, in one place."""

    model_config = SettingsConfigDict(
        env_prefix="PIPESENTRY_", env_nested_delimiter="__", extra="forbid", allow_inf_nan=False
    )

    database: DatabaseSettings = DatabaseSettings()
    retention: RetentionSettings = RetentionSettings()
    logging: LoggingSettings = LoggingSettings()
    metrics: MetricsSettings = MetricsSettings()
    alerting: AlertingSettings = AlertingSettings()  # [alerting] and [[alerting.sinks]], see docs/alerting.md
    uplink: UplinkSettings | None = None  # [uplink]: store-and-forward to a central PipeSentry
    reopen_backoff_max_s: float = Field(
        60.0, gt=0, le=DAY_S, description="cap of the exponential backoff to reopen a port"
    )
    shutdown_timeout_s: float = Field(5.0, gt=0, le=MAX_TIMEOUT_S)
    watchdog_stall_s: float = Field(
        0.0, ge=0, le=MAX_INTERVAL_S, description="a worker without progress for this long stops watchdog pings (0 = 3 x interval)"
    )
    nodes: list[NodeSettings] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique_nodes(self) -> GatewaySettings:
        ids = [n.id for n in self.nodes]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"node ids must be unique, repeated: {', '.join(dup)}")
        by_port: dict[str, list[str]] = {}
        for n in self.nodes:
            if not n.url.startswith("loop://"):
                by_port.setdefault(n.port_key, []).append(n.url)
        shared = [" and ".join(urls) if len(set(urls)) > 1 else urls[0] for urls in by_port.values() if len(urls) > 1]
        if shared:
            raise ValueError(f"two nodes share a port: {', '.join(shared)}")
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # Highest priority first: the environment, then the file's contents (passed as arguments).
        return (env_settings, init_settings)


def _format_errors(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        key = ".".join(str(p) for p in err["loc"]) or "(top level)"
        message = err["msg"].removeprefix("Value error, ")
        parts.append(f"{key}: {message}")
    return "; ".join(parts)


def _read_toml(path: Path) -> dict:
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a config file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line}); "
                          "TOML files are UTF-8") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None


class DeliverySettings(BaseSettings):
    """What alert delivery alone needs (``pipesentry alerts deliver`` at a central site: no nodes to poll)."""

    model_config = SettingsConfigDict(
        env_prefix="PIPESENTRY_", env_nested_delimiter="__", extra="forbid", allow_inf_nan=False
    )

    database: DatabaseSettings = DatabaseSettings()
    logging: LoggingSettings = LoggingSettings()
    alerting: AlertingSettings = AlertingSettings()
    shutdown_timeout_s: float = Field(5.0, gt=0, le=MAX_TIMEOUT_S)


def load_delivery_settings(path: str | Path) -> GatewaySettings | DeliverySettings:
    """A gateway config (it has ``[[nodes]]``: checked whole), or a delivery-only one (``[database]``,
    ``[alerting]``, ``[logging]``, ``shutdown_timeout_s``); raise ConfigError naming every offending key."""
    path = Path(path)
    data = _read_toml(path)
    if "nodes" in data:
        return settings_from_mapping(data, source=str(path))
    try:
        return DeliverySettings(**data)
    except ValidationError as exc:
        raise ConfigError(f"{path}: {_format_errors(exc)}") from None
    except SettingsError as exc:
        raise ConfigError(f"{path}: {_environment_error(exc)}") from None


def load_settings(path: str | Path) -> GatewaySettings:
    """Read and validate the gateway config; raise ConfigError naming every offending key.

    Opens nothing: the database URL, ports and sinks are checked as far as that is possible
    without connecting (see :func:`db.urls.check_database_url`)."""
    path = Path(path)
    return settings_from_mapping(_read_toml(path), source=str(path))


def settings_from_mapping(data: dict, source: str) -> GatewaySettings:
    """Validate a parsed config (the environment still wins); ConfigError messages start with ``source``."""
    try:
        return GatewaySettings(**data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {_format_errors(exc)}") from None
    except SettingsError as exc:  # a PIPESENTRY_* variable that is not the JSON its field needs
        raise ConfigError(f"{source}: {_environment_error(exc)}") from None


def _environment_error(exc: SettingsError) -> str:
    """Which variable is malformed, in one line (pydantic-settings' message names the field)."""
    cause = exc.__cause__
    detail = f" ({cause})" if isinstance(cause, ValueError) else ""
    field = str(exc).partition('field "')[2].partition('"')[0]
    variable = f"PIPESENTRY_{field.upper()}" if field else "a PIPESENTRY_* variable"
    return f"environment variable {variable} is not valid JSON for that setting{detail}"
