"""`pipesentry gateway --config gateway.toml`: run the gateway daemon."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from pipesentry.errors import fail


def gateway(
    config: Annotated[Path, typer.Option(help="gateway TOML config: docs/gateway.md, examples/gateway-*.toml")],
    check: Annotated[bool, typer.Option("--check", help="validate the config and exit")] = False,
) -> None:
    """Poll the configured nodes, store traces and DI maps, recompute the map, flag damage."""
    from gateway.blas_threads import one_blas_thread

    one_blas_thread(os.environ)  # before numpy loads (gateway.config imports it): one core per node worker
    from gateway.config import ConfigError, load_settings
    from gateway.daemon import run
    from gateway.logs import setup_logging

    try:
        settings = load_settings(config)
    except ConfigError as exc:
        fail(str(exc))
    if check:
        typer.echo(f"{config}: ok, {len(settings.nodes)} node(s)")
        return
    setup_logging(settings.logging.level, settings.logging.json_lines)
    raise typer.Exit(run(settings))
