"""`pipesentry alerts deliver --config gateway.toml`: run alert delivery alone (no node polling);
`pipesentry alerts schema`: print the JSON Schema of the alert payload.

Delivery alone is for a deployment that runs it apart from the gateway, and for draining the
outbox by hand; it reads the same config and database. Exit codes: 0 stopped by
SIGTERM/SIGINT, 2 bad config or database. ``python -m alerts deliver`` is the same command
(alerts/__main__.py).
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipesentry.errors import fail

alerts_app = typer.Typer(help="Alert delivery (the gateway runs it itself; see docs/alerting.md).",
                         no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


@alerts_app.command("deliver")
def deliver(
    config: Annotated[Path, typer.Option(help="the gateway TOML config, or a delivery-only one without [[nodes]] "
                                               "(a central site: docs/deploy.md)")],
    no_watch: Annotated[
        bool, typer.Option("--no-watch", help="only deliver: raise no node_offline/node_online or baseline_changed events")
    ] = False,
) -> None:
    """Send the outbox to the configured sinks until stopped."""
    import logging
    import signal
    import threading

    from alerts.delivery import AlertDelivery
    from db.database import open_database
    from db.errors import StorageError
    from gateway.config import ConfigError, load_delivery_settings
    from gateway.logs import setup_logging

    try:
        settings = load_delivery_settings(config)
    except ConfigError as exc:
        fail(str(exc))
    try:
        database = open_database(settings.database.url, upgrade=False)
    except StorageError as exc:
        fail(str(exc))
    setup_logging(settings.logging.level, settings.logging.json_lines)  # after the checks: their error is one line
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    delivery = AlertDelivery(settings.alerting, database, stop=stop, watch_fleet=not no_watch)
    delivery.start()
    logging.getLogger("pipesentry.alerts").info("delivering to %d sink(s)", len(delivery.sink_workers))
    while not stop.wait(1.0):  # signal handlers run between waits
        pass
    delivery.join(settings.shutdown_timeout_s)
    database.dispose()


@alerts_app.command("schema")
def schema() -> None:
    """Print the JSON Schema of the payload every sink is given (docs/alerting.md)."""
    import json

    from alerts.payloads import payload_json_schema

    typer.echo(json.dumps(payload_json_schema(), indent=2))
