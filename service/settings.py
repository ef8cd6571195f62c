"""The API server's settings: one pydantic-settings class, overridable by PIPESENTRY_API_* variables."""
from __future__ import annotations

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from db.urls import DatabaseUrlError, check_database_url
from service.database import DEFAULT_INTEGRITY_CHECK_EVERY_S, DEFAULT_MIN_FREE_BYTES

KIB = 1024


class ApiSettings(BaseSettings):
    """Everything ``pipesentry api`` needs; e.g. ``PIPESENTRY_API_DATABASE_URL=sqlite:////var/lib/ps.db``."""

    model_config = SettingsConfigDict(env_prefix="PIPESENTRY_API_", extra="forbid")

    database_url: str = Field("sqlite:///pipesentry.db", description="the gateway's database (read; API writes operator actions)")
    host: str = Field("127.0.0.1", description="listen address; put a TLS-terminating proxy in front for remote access")
    port: int = Field(8000, ge=1, le=65535)
    base_path: str = Field("/api/v1", description="prefix of every API route")
    cors_origins: list[str] = Field(
        default_factory=list, description="browser origins allowed to call the API cross-site (empty = CORS off)"
    )
    max_body_bytes: int = Field(64 * KIB, ge=1, description="larger request bodies get 413")
    metrics_require_key: bool = Field(
        True, description="/metrics needs a key (any role) unless this is false (trusted scrape network only)"
    )
    dashboard_refresh_s: float = Field(10.0, ge=1.0, le=3600.0, description="how often the dashboard reloads its data")
    busy_timeout_ms: int = Field(5000, ge=0, description="SQLite: how long a write waits for the gateway's lock")
    request_timeout_s: float = Field(
        10.0, gt=0, le=300, description="a request's head and body must arrive within this long of the connection "
        "opening (or of the previous response on it): slow or silent clients are answered 408 and closed"
    )
    max_connections: int = Field(
        768, ge=1, le=100_000, description="open connections at most; beyond it the one waiting longest for its "
        "request is closed (keep it below the process's open-file limit: 1024 under systemd by default)"
    )
    max_requests_in_flight: int = Field(
        512, ge=1, le=100_000, description="requests handled at once at most; the next get a 503 server-busy problem"
    )
    integrity_check_every_s: float = Field(
        DEFAULT_INTEGRITY_CHECK_EVERY_S, gt=0, le=7 * 86_400, allow_inf_nan=False,
        description="SQLite: PRAGMA quick_check when opened and again this often (a damaged file: /readyz 503)",
    )
    min_free_bytes: int = Field(
        DEFAULT_MIN_FREE_BYTES, ge=0, description="SQLite: less free space than this on the database's filesystem "
        "is /readyz 503 storage_unavailable (the gateway cannot store its next measurement)",
    )
    key_cache_ttl_s: float = Field(
        10.0, ge=0, le=300, description="a verified API key is trusted this long without a lookup; a key revoked "
        "outside this process stops working within it (0: look up every request)"
    )

    # The central site (docs/deploy.md): gateways POST their records to /ingest/batches.
    ingest_max_body_bytes: int = Field(
        8 * 1024 * KIB, ge=KIB, le=64 * 1024 * KIB,
        description="an ingest batch's body, after gzip is undone, larger gets 413 (the contract's limit: 8 MiB)",
    )
    ingest_concurrency: int = Field(
        4, ge=1, le=64, description="ingest batches stored at once per worker; more get 429 with Retry-After"
    )
    ingest_retry_after_s: int = Field(2, ge=1, le=600, description="Retry-After of a 429 from a busy ingest")
    central_alert_sinks: list[str] = Field(
        default_factory=list, description="sinks the centre delivers a gateway's alerts to when the gateway leaves "
        "them to the centre (names of `alerts deliver`'s sinks; empty: the centre sends no edge alert)",
    )

    @field_validator("database_url")
    @classmethod
    def _usable_database_url(cls, value: str) -> str:
        """A URL that cannot work refuses the start (a missing file is fine: /readyz says so until it exists)."""
        try:
            check_database_url(value)
        except DatabaseUrlError as exc:
            raise ValueError(str(exc)) from None
        return value

    @field_validator("base_path")
    @classmethod
    def _base_path_shape(cls, value: str) -> str:
        if not value.startswith("/") or value.endswith("/") or len(value) < 2:
            raise ValueError("base_path must start with '/' and not end with '/', e.g. /api/v1")
        return value
