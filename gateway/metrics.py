"""The gateway's own Prometheus metrics, served on ``[metrics] host:port`` (prometheus_client).

What only the running daemon knows: its poll cycles, failures and retries per node, each node's
configured interval (so a rule can tell one silent node among healthy ones), its delivery
attempts and failures per sink, the last acknowledged delivery and the outbox depth per sink,
plus ``pipesentry_build_info`` and the process' own series. The stored state of the fleet (node
states, DI, deliveries per status) is the API's ``/metrics`` (service/metrics.py); which process
exposes what is in docs/api.md. Read at scrape time from the workers, no global registry.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from wsgiref.simple_server import WSGIServer

from prometheus_client import CollectorRegistry, Info, ProcessCollector, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from alerts.delivery import SinkWorker
from alerts.outbox import delivery_counts
from db.database import Database
from db.errors import StorageError
from db.models import DeliveryStatus
from db.release import release_labels
from gateway.config import MetricsSettings
from gateway.worker import NodeWorker

log = logging.getLogger("pipesentry.gateway")

# Each failed cycle is counted once, under the first thing that went wrong.
FAILURE_REASONS = {
    "node": "failures",  # the node did not answer as it should: timeouts, CRC, transfers, node errors
    "port": "port_reopens",  # the port vanished, could not be opened, or speaks another protocol
    "storage": "storage_errors",  # the measurement could not be stored (disk full, database locked)
    "internal": "internal_errors",  # a bug in the gateway (logged with its traceback)
}


class GatewayCollector(Collector):
    """Per node and per sink, what this gateway process did since it started."""

    def __init__(self, nodes: Sequence[NodeWorker], sinks: Sequence[SinkWorker], database: Database) -> None:
        self.nodes = nodes
        self.sinks = sinks
        self.database = database

    def collect(self) -> Iterator[Metric]:
        yield from self._storage_metrics()
        yield from self._node_metrics()
        yield from self._sink_metrics()

    def _storage_metrics(self) -> Iterator[Metric]:
        available = GaugeMetricFamily("pipesentry_gateway_storage_available",
                                      "1 while the gateway's writes work; 0 since one failed (disk full, I/O error, "
                                      "read-only) until one fits again")
        since = GaugeMetricFamily("pipesentry_gateway_storage_unavailable_since_timestamp_seconds",
                                  "when the writes started failing (absent while they work)")
        failed = GaugeMetricFamily("pipesentry_gateway_storage_failed_writes",
                                   "writes refused in the outage going on (absent while they work)")
        damaged = GaugeMetricFamily("pipesentry_gateway_database_damaged",
                                    "1 once the database was found damaged (nothing more is written; the gateway stops)")
        outage = self.database.storage_outage
        available.add_metric([], 0.0 if outage is not None else 1.0)
        damaged.add_metric([], 0.0 if self.database.damage is None else 1.0)
        yield from (available, damaged)
        if outage is not None:
            since.add_metric([], outage.since.timestamp())
            failed.add_metric([], outage.failed_writes)
            yield from (since, failed)

    def _node_metrics(self) -> Iterator[Metric]:
        node = ["node"]
        interval = GaugeMetricFamily("pipesentry_node_interval_seconds",
                                     "the node's configured time between measurements (nodes in service)", labels=node)
        cycles = CounterMetricFamily("pipesentry_gateway_node_cycles", "poll cycles started on the node's open port",
                                     labels=node)
        failed = CounterMetricFamily("pipesentry_gateway_node_cycle_failures",
                                     "cycles (or port openings) that stored no measurement, by first cause",
                                     labels=["node", "reason"])
        transfers = CounterMetricFamily("pipesentry_gateway_node_transfer_failures",
                                        "bulk transfers (traces, DI map) given up on", labels=node)
        timeouts = CounterMetricFamily("pipesentry_gateway_node_timeouts",
                                       "commands without a reply after every retry", labels=node)
        retries = CounterMetricFamily("pipesentry_gateway_node_retries",
                                      "commands and chunk requests sent again (lost, late or corrupt replies)",
                                      labels=node)
        for worker in self.nodes:
            name = worker.settings.id
            counters = worker.counters
            if not worker.out_of_service:
                interval.add_metric([name], worker.settings.interval_s)
            cycles.add_metric([name], counters.cycles)
            for reason, field in FAILURE_REASONS.items():
                failed.add_metric([name, reason], getattr(counters, field))
            transfers.add_metric([name], counters.transfer_errors)
            timeouts.add_metric([name], counters.timeouts)
            retries.add_metric([name], worker.retries_total())
        yield from (interval, cycles, failed, transfers, timeouts, retries)

    def _sink_metrics(self) -> Iterator[Metric]:
        sink = ["sink"]
        attempts = CounterMetricFamily("pipesentry_gateway_alert_attempts", "deliveries of outbox events tried",
                                       labels=sink)
        failures = CounterMetricFamily("pipesentry_gateway_alert_failures",
                                       "delivery attempts that failed (each is retried until max_attempts)", labels=sink)
        delivered = GaugeMetricFamily("pipesentry_gateway_alert_last_delivery_timestamp_seconds",
                                      "when the sink's receiver last acknowledged a delivery (absent: not yet)",
                                      labels=sink)
        depth = GaugeMetricFamily("pipesentry_gateway_alert_queue_depth",
                                  "deliveries waiting in the outbox for the sink (pending)", labels=sink)
        try:
            with self.database.session() as session:
                pending = {sink: n for (sink, status), n in delivery_counts(session).items()
                           if status == DeliveryStatus.PENDING}
        except StorageError as error:  # the depth is left out; the counters still tell
            log.warning("gateway metrics: outbox unreadable: %s", error)
            pending = None
        for worker in self.sinks:
            name = worker.sink.name
            stats = worker.stats
            attempts.add_metric([name], stats.attempts)
            failures.add_metric([name], stats.failures)
            if stats.last_delivered_at is not None:
                delivered.add_metric([name], stats.last_delivered_at.timestamp())
            if pending is not None:
                depth.add_metric([name], pending.get(name, 0))
        yield from (attempts, failures, delivered)
        if pending is not None:
            yield depth


def gateway_registry(nodes: Sequence[NodeWorker], sinks: Sequence[SinkWorker], database: Database) -> CollectorRegistry:
    """The gateway's registry: its collector, ``pipesentry_build_info`` and the process' series."""
    registry = CollectorRegistry(auto_describe=False)
    Info("pipesentry_build", "the running PipeSentry release", registry=registry).info(release_labels())
    ProcessCollector(registry=registry)
    registry.register(GatewayCollector(nodes, sinks, database))
    return registry


@dataclass
class MetricsServer:
    """prometheus_client's HTTP server in its own thread; ``port`` is the bound one (0 in the config: any)."""

    server: WSGIServer
    thread: threading.Thread

    @property
    def port(self) -> int:
        return int(self.server.server_port)

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5.0)


def serve_metrics(settings: MetricsSettings, registry: CollectorRegistry) -> MetricsServer | None:
    """Serve ``registry`` on ``settings.host:port``; None (logged) when off or the address is taken.

    A taken port does not stop the gateway: monitoring the pipes matters more than its metrics,
    and the scrape's ``up == 0`` (PipeSentryGatewayDown) tells the operator.
    """
    if not settings.enabled:
        return None
    try:
        server, thread = start_http_server(settings.port, addr=settings.host, registry=registry)
    except OSError as exc:
        log.error("metrics not served: cannot listen on %s:%d: %s", settings.host, settings.port, exc)
        return None
    served = MetricsServer(server, thread)
    log.info("metrics on http://%s:%d/metrics", settings.host, served.port)
    return served
