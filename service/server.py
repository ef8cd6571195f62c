"""How uvicorn serves the app: one place for ``pipesentry api`` and the tests, so both run the same limits."""
from __future__ import annotations

import copy
import functools
from typing import Any

import uvicorn
from fastapi import FastAPI

from service.connection_guard import GuardedHttpProtocol, guarded_protocol
from service.settings import ApiSettings

APP_FROM_ENV = "service.app:app_from_env"  # what each worker process builds (``--workers`` above 1)
WORKER_PROTOCOL = "service.server:WorkerGuardedHttpProtocol"


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


@functools.cache
def _worker_limits() -> tuple[float, int]:
    settings = ApiSettings()
    return settings.request_timeout_s, settings.max_connections


class WorkerGuardedHttpProtocol(GuardedHttpProtocol):
    """The guarded protocol for worker processes, which import it by name (a configured class made by
    :func:`guarded_protocol` cannot cross into a spawned process): the limits are the worker's own
    ApiSettings, read from the environment the parent validated. ``max_connections`` is per worker."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.request_timeout_s, self.max_connections = _worker_limits()


def uvicorn_config(app: FastAPI | str, settings: ApiSettings, *, port: int | None = None, log_level: str = "info",
                   logging_config: dict[str, Any] | None = None, workers: int = 1) -> uvicorn.Config:
    """uvicorn's settings for ``app``: the guarded protocol (service/connection_guard.py), no proxy headers.

    ``limit_concurrency`` stays off: uvicorn counts idle connections against it (a few hundred
    half-open ones made every answer a 503); the app's :class:`service.limits.RequestsInFlightLimit`
    bounds the requests being handled instead.

    ``workers`` above 1 (a central site on PostgreSQL): ``app`` is :data:`APP_FROM_ENV`, which each
    worker process builds from the environment; serve the config with :func:`serve_workers`.
    """
    several = workers > 1
    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port if port is None else port,
        http=WORKER_PROTOCOL if several
        else guarded_protocol(request_timeout_s=settings.request_timeout_s, max_connections=settings.max_connections),
        factory=several,
        workers=workers if several else None,
        log_level=log_level,
        log_config=logging_config or uvicorn.config.LOGGING_CONFIG,  # pipesentry api: log_config()
        proxy_headers=False,
        server_header=False,
        timeout_graceful_shutdown=5,
        lifespan="on",
    )


def serve_workers(config: uvicorn.Config) -> None:
    """Serve ``config`` (``workers`` above 1) with uvicorn's supervisor: the workers share one socket."""
    from uvicorn.supervisors import Multiprocess

    Multiprocess(config, sockets=[config.bind_socket()]).run()
