"""How uvicorn serves the app: one place for ``pipesentry api`` and the tests, so both run the same limits."""
from __future__ import annotations

import uvicorn
from fastapi import FastAPI

from service.connection_guard import guarded_protocol
from service.settings import ApiSettings


def uvicorn_config(app: FastAPI, settings: ApiSettings, *, port: int | None = None, log_level: str = "info",
                   log_config: dict | None = None) -> uvicorn.Config:
    """uvicorn's settings for ``app``: the guarded protocol (service/connection_guard.py), no proxy headers.

    ``limit_concurrency`` stays off: uvicorn counts idle connections against it (a few hundred
    half-open ones made every answer a 503); the app's :class:`service.limits.RequestsInFlightLimit`
    bounds the requests being handled instead.
    """
    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port if port is None else port,
        http=guarded_protocol(request_timeout_s=settings.request_timeout_s, max_connections=settings.max_connections),
        log_level=log_level,
        log_config=log_config if log_config is not None else uvicorn.config.LOGGING_CONFIG,
        proxy_headers=False,
        server_header=False,
        timeout_graceful_shutdown=5,
        lifespan="on",
    )
