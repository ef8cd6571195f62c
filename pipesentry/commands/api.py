"""`pipesentry api`: serve the operator API and dashboard with uvicorn."""
from __future__ import annotations

import contextlib
from typing import Annotated, Any

import typer

from pipesentry.errors import fail

STARTUP_FAILURE = 3  # uvicorn's exit code when the server did not start


def api(
    database_url: Annotated[
        str | None, typer.Option(help="the gateway's database URL (env PIPESENTRY_API_DATABASE_URL)")
    ] = None,
    host: Annotated[str | None, typer.Option(help="listen address (env PIPESENTRY_API_HOST; default 127.0.0.1)")] = None,
    port: Annotated[int | None, typer.Option(help="listen port (env PIPESENTRY_API_PORT; default 8000)")] = None,
    log_level: Annotated[str, typer.Option(help="uvicorn log level")] = "info",
    workers: Annotated[int, typer.Option(min=1, max=64, help="worker processes (a central site on PostgreSQL: "
                                         "several; they share nothing but the database)")] = 1,
) -> None:
    """Serve the operator API (/api/v1), /healthz, /readyz, /metrics and the dashboard at /.

    Other settings (CORS origins, body limit, base path, whether /metrics needs a key) come
    from PIPESENTRY_API_* environment variables; see docs/api.md.
    """
    import os

    import uvicorn
    from pydantic import ValidationError

    from service.app import create_app
    from service.server import APP_FROM_ENV, log_config, serve_workers, uvicorn_config
    from service.settings import ApiSettings

    overrides: dict[str, Any] = {k: v for k, v in {"database_url": database_url, "host": host, "port": port}.items() if v is not None}
    try:
        settings = ApiSettings(**overrides)
    except ValidationError as exc:
        fail("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg'].removeprefix('Value error, ')}" for e in exc.errors()))
    if workers > 1 and settings.database_url.startswith("sqlite"):
        fail("--workers above 1 needs PostgreSQL (a central site); SQLite takes one writer: serve it with one worker")
    if workers > 1:
        # Each worker process builds its own app from the environment (the same settings, as validated here).
        os.environ.update({f"PIPESENTRY_API_{name.upper()}": str(value) for name, value in overrides.items()})
        with contextlib.suppress(KeyboardInterrupt):
            serve_workers(uvicorn_config(APP_FROM_ENV, settings, log_level=log_level, workers=workers,
                                         logging_config=log_config()))
        return
    server = uvicorn.Server(uvicorn_config(create_app(settings), settings, log_level=log_level,
                                           logging_config=log_config()))
    with contextlib.suppress(KeyboardInterrupt):
        server.run()
    if not server.started:  # as uvicorn.run: the port was taken or the app did not start
        raise typer.Exit(STARTUP_FAILURE)
