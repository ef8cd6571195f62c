"""``python -m alerts deliver --config gateway.toml``: run alert delivery alone (no node polling).

For a deployment that runs delivery apart from the gateway, and for draining the outbox by
hand; it reads the same config and database. Exit codes: 0 stopped by SIGTERM/SIGINT,
2 bad config or database.
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from alerts.delivery import AlertDelivery
from db.database import open_database
from db.errors import StorageError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m alerts", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    deliver = sub.add_parser("deliver", help="send the outbox to the configured sinks until stopped")
    deliver.add_argument("--config", required=True, help="the gateway TOML config")
    deliver.add_argument("--no-watch", action="store_true",
                         help="only deliver: raise no node_offline/node_online or baseline_changed events")
    args = parser.parse_args(argv)

    from gateway.config import ConfigError, load_settings

    try:
        settings = load_settings(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=settings.logging.level, format="%(asctime)s %(levelname)s %(threadName)s %(message)s")
    try:
        database = open_database(settings.database.url, upgrade=False)
    except StorageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    delivery = AlertDelivery(settings.alerting, database, stop=stop, watch_fleet=not args.no_watch)
    delivery.start()
    logging.getLogger("pipesentry.alerts").info("delivering to %d sink(s)", len(delivery.sink_workers))
    while not stop.wait(1.0):  # signal handlers run between waits
        pass
    delivery.join(settings.shutdown_timeout_s)
    database.dispose()
    return 0


if __name__ == "__main__":
    sys.exit(main())
