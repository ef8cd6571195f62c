"""The gateway's own Prometheus metrics, served on ``[metrics] host:port`` (prometheus_client).

What only the running daemon knows: its poll cycles, failures and retries per node, each node's
configured interval (so a rule can tell one silent node among healthy ones), its delivery
attempts and failures per sink, the last acknowledged delivery and the outbox depth per sink,
plus ``pipesentry_build_info`` and the process' own series. The stored state of the fleet (node
states, DI, deliveries per status) is the API's ``/metrics`` (service/metrics.py); which process
exposes what is in docs/api.md. Read at scrape time from the workers, no global registry.
"""
from __future__ import annotations

import json
import logging
import socket
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, Info, ProcessCollector, make_wsgi_app
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import Collector

from alerts.delivery import SinkWorker
from alerts.outbox import delivery_counts
from db.database import Database
from db.errors import StorageError
from db.models import DeliveryStatus
from db.release import release_labels
from db.uplink_queue import queue_stats
from gateway.config import MetricsSettings
from gateway.uplink.sender import UplinkSender
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

    def __init__(self, nodes: Sequence[NodeWorker], sinks: Sequence[SinkWorker], database: Database,
                 uplink: UplinkSender | None = None) -> None:
        self.nodes = nodes
        self.sinks = sinks
        self.database = database
        self.uplink = uplink

    def collect(self) -> Iterator[Metric]:
        yield from self._storage_metrics()
        yield from self._node_metrics()
        yield from self._sink_metrics()
        if self.uplink is not None:
            yield from self._uplink_metrics(self.uplink)

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
        gain = GaugeMetricFamily("pipesentry_node_baseline_gain",
                                 "the receivers' common gain the last imaged record's baseline was scaled by "
                                 "(1: none; the ring's drift since that baseline)", labels=node)
        stretch = GaugeMetricFamily("pipesentry_node_baseline_stretch",
                                    "the time-stretch the last imaged record's baseline was matched with "
                                    "(about 1e-4 per degC from that baseline's temperature)", labels=node)
        offset = GaugeMetricFamily("pipesentry_node_thermometer_offset_celsius",
                                   "how much further the node's thermometer says the pipe's temperature moved since "
                                   "the last imaged record's baseline than the wave's stretch says (about 0; a "
                                   "drifting or misplaced sensor grows it)", labels=node)
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
            if worker.last_match is not None:
                gain.add_metric([name], worker.last_match[0])
                stretch.add_metric([name], worker.last_match[1])
                if worker.last_match[2] is not None:
                    offset.add_metric([name], worker.last_match[2])
        yield from (interval, cycles, failed, transfers, timeouts, retries, gain, stretch, offset)

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


    def _uplink_metrics(self, uplink: UplinkSender) -> Iterator[Metric]:
        stats = uplink.stats
        counters = (
            ("batches", "batches the centre stored", stats.batches),
            ("records", "records in them (new at the centre or already held)", stats.records),
            ("duplicates", "records the centre already held (re-sent after a lost answer)", stats.duplicates),
            ("failures", "batches sent that the centre did not store (link down, busy, refused)", stats.failures),
        )
        for name, doc, value in counters:
            yield CounterMetricFamily(f"pipesentry_gateway_uplink_{name}", doc, value=value)
        answered = CounterMetricFamily("pipesentry_gateway_uplink_trace_requests",
                                       "the centre's requests for traces answered, by answer (held: queued with "
                                       "them; pruned: retention removed them)", labels=["answer"])
        for answer, count in sorted(stats.trace_answers.items()):
            answered.add_metric([answer], count)
        yield answered
        yield CounterMetricFamily("pipesentry_gateway_uplink_trace_request_failures",
                                  "polls for the centre's trace requests, or deliveries of the answers, that failed "
                                  "(asked again after requests_every_s)", value=stats.requests_failures)
        if stats.last_stored_at is not None:
            yield GaugeMetricFamily("pipesentry_gateway_uplink_last_stored_timestamp_seconds",
                                    "when the centre last stored a batch", value=stats.last_stored_at.timestamp())
        try:
            with self.database.session() as session:
                queue = queue_stats(session)
        except StorageError as error:  # the queue's figures are left out; the counters still tell
            log.warning("gateway metrics: uplink queue unreadable: %s", error)
            return
        yield GaugeMetricFamily("pipesentry_gateway_uplink_queue_depth",
                                "records waiting for the centre to acknowledge them", value=queue.depth)
        yield GaugeMetricFamily("pipesentry_gateway_uplink_lag_seconds",
                                "how long the oldest unsent record has waited (0: nothing waits)",
                                value=queue.lag_s(uplink.clock()))
        yield GaugeMetricFamily("pipesentry_gateway_uplink_refused_records",
                                "records the centre refused, set aside (kept here, not sent)", value=queue.refused)
        if queue.oldest_pending_at is not None:
            yield GaugeMetricFamily("pipesentry_gateway_uplink_oldest_unsent_timestamp_seconds",
                                    "when the oldest unsent record was queued (absent: nothing waits)",
                                    value=queue.oldest_pending_at.timestamp())


def gateway_registry(nodes: Sequence[NodeWorker], sinks: Sequence[SinkWorker], database: Database,
                     uplink: UplinkSender | None = None) -> CollectorRegistry:
    """The gateway's registry: its collector, ``pipesentry_build_info`` and the process' series."""
    registry = CollectorRegistry(auto_describe=False)
    Info("pipesentry_build", "the running PipeSentry release", registry=registry).info(release_labels())
    ProcessCollector(registry=registry)
    registry.register(GatewayCollector(nodes, sinks, database, uplink))
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


# The gateway's readiness: (ready, what it says); served as /readyz beside /metrics.
Readiness = Callable[[], tuple[bool, dict[str, Any]]]


class _QuietHandler(WSGIRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:
        """Scrapes are not logged (one line per scrape every few seconds)."""


def metrics_app(registry: CollectorRegistry, readiness: Readiness | None = None) -> Callable[..., Iterable[bytes]]:
    """A WSGI app: ``/readyz`` answers the readiness (200 ready, 503 not, JSON), any other path the metrics."""
    metrics = make_wsgi_app(registry)

    def app(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
        if environ.get("PATH_INFO") != "/readyz" or readiness is None:
            return metrics(environ, start_response)
        try:
            ready, body = readiness()
        except StorageError as error:
            ready, body = False, {"status": "not ready", "reasons": [f"database unreadable: {error}"]}
        payload = json.dumps(body).encode()
        start_response("200 OK" if ready else "503 Service Unavailable",
                       [("Content-Type", "application/json"), ("Content-Length", str(len(payload)))])
        return [payload]

    return app


def serve_metrics(settings: MetricsSettings, registry: CollectorRegistry,
                  readiness: Readiness | None = None) -> MetricsServer | None:
    """Serve ``registry`` on ``settings.host:port`` (and ``readiness`` as ``/readyz``); None (logged)
    when off or the address is taken.

    A taken port does not stop the gateway: monitoring the pipes matters more than its metrics,
    and the scrape's ``up == 0`` (PipeSentryGatewayDown) tells the operator.
    """
    if not settings.enabled:
        return None
    class Server(ThreadingWSGIServer):
        address_family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET

    try:
        server = make_server(settings.host, settings.port, metrics_app(registry, readiness), Server,
                             handler_class=_QuietHandler)
    except OSError as exc:
        log.error("metrics not served: cannot listen on %s:%d: %s", settings.host, settings.port, exc)
        return None
    thread = threading.Thread(target=server.serve_forever, name="metrics", daemon=True)
    thread.start()
    served = MetricsServer(server, thread)
    log.info("metrics on http://%s:%d/metrics", settings.host, served.port)
    return served
