"""How uvicorn serves the app: one place for ``pipesentry api`` and the tests, so both run the same limits."""
from __future__ import annotations

import copy
from typing import Any

import uvicorn
from fastapi import FastAPI

from service.connection_guard import guarded_protocol
from service.settings import ApiSettings


def log_config() -> dict[str, Any]:
    """uvicorn's logging, and the API's own loggers (``pipesentry.*``) through the shared safe formatter.

    For the API's own process (``pipesentry api``): it takes the ``pipesentry`` loggers over.

    Operator-supplied text the API logs (a decommissioning's reason, a key's name) is written on
    one line with its control characters escaped (db/log_text.py).
    """
    config = copy.deepcopy(uvicorn.config.LOGGING_CONFIG)
    config["formatters"]["pipesentry"] = {"()": "db.log_text.SafeFormatter",
                                          "fmt": "%(asctime)s %(levelname)s %(name)s: %(message)s"}
    config["handlers"]["pipesentry"] = {"formatter": "pipesentry", "class": "logging.StreamHandler",
                                        "stream": "ext://sys.stderr"}
    config["loggers"]["pipesentry"] = {"handlers": ["pipesentry"], "level": "INFO", "propagate": False}
    return config


def uvicorn_config(app: FastAPI, settings: ApiSettings, *, port: int | None = None, log_level: str = "info",
                   logging_config: dict[str, Any] | None = None) -> uvicorn.Config:
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
        log_config=logging_config or uvicorn.config.LOGGING_CONFIG,  # pipesentry api: log_config()
        proxy_headers=False,
        server_header=False,
        timeout_graceful_shutdown=5,
        lifespan="on",
    )
