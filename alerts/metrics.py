"""Prometheus metrics of alert delivery per sink, read from the outbox at scrape time.

For the API's ``/metrics``: ``registry.register(AlertDeliveryCollector(gate.get))``: the stored
deliveries per sink and status (fleet-wide totals are ``sum without (sink)``), which
``docker/prometheus/alerts.yml`` alerts on. The attempts a gateway makes are its own metrics
(gateway/metrics.py).
``SensorFaultCollector(gate.get)`` adds ``pipesentry_node_faulty_receivers{node}``: the
receivers of each node in service with an open ``sensor_fault`` alert (0 for every other node).
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from alerts.events import EventKind
from alerts.outbox import delivery_counts, events_of_kind, oldest_pending_age_s
from alerts.sensor_faults import open_sensor_faults_by_node
from db.database import Database
from db.errors import StorageError
from db.models import DeliveryStatus
from db.nodes import list_nodes

log = logging.getLogger("pipesentry.alerts")

SINK_DELIVERIES = "pipesentry_alert_sink_deliveries"
SINK_OLDEST_PENDING_AGE = "pipesentry_alert_sink_oldest_pending_age_seconds"
SINK_DISABLED = "pipesentry_alert_sink_disabled_timestamp_seconds"
NODE_FAULTY_RECEIVERS = "pipesentry_node_faulty_receivers"


class AlertDeliveryCollector(Collector):
    """Deliveries per sink and status, age of each sink's oldest pending event, 410-disabled sinks."""

    def __init__(self, get_database: Callable[[], Database]) -> None:
        self.get_database = get_database

    def collect(self) -> Iterator[Metric]:
        deliveries = GaugeMetricFamily(SINK_DELIVERIES, "alert deliveries per sink and status",
                                       labels=["sink", "status"])
        oldest = GaugeMetricFamily(SINK_OLDEST_PENDING_AGE, "how long the oldest undelivered event has waited",
                                   labels=["sink"])
        disabled = GaugeMetricFamily(SINK_DISABLED, "when a sink's receiver answered 410 Gone (sink disabled)",
                                     labels=["sink"])
        try:
            with self.get_database().session() as session:
                counts = delivery_counts(session)
                ages = oldest_pending_age_s(session)
                gone = events_of_kind(session, EventKind.SINK_DISABLED, newest_first=False)
                gone_at = {str(e.payload.get("sink")): e.created_at.timestamp() for e in gone}
        except StorageError as error:
            log.warning("alert metrics: database unavailable: %s", error)
            return
        sinks = sorted({sink for sink, _ in counts})
        for sink in sinks:
            for status in DeliveryStatus:
                deliveries.add_metric([sink, status.value], float(counts.get((sink, status), 0)))
            oldest.add_metric([sink], ages.get(sink, 0.0))
        for sink, at in sorted(gone_at.items()):
            disabled.add_metric([sink], at)
        yield from (deliveries, oldest, disabled)


class SensorFaultCollector(Collector):
    """Receivers per node with an open sensor_fault alert (debounced as the alerts are)."""

    def __init__(self, get_database: Callable[[], Database]) -> None:
        self.get_database = get_database

    def collect(self) -> Iterator[Metric]:
        faulty = GaugeMetricFamily(NODE_FAULTY_RECEIVERS, "receivers of the node with an open sensor_fault alert "
                                   "(left out of its DI map)", labels=["node"])
        try:
            with self.get_database().session() as session:
                nodes = [n.node_id for n in list_nodes(session, include_decommissioned=False)]
                open_faults = open_sensor_faults_by_node(session)
        except StorageError as error:
            log.warning("sensor fault metrics: database unavailable: %s", error)
            return
        for node_id in nodes:  # the nodes in service, as the fleet's metrics
            faulty.add_metric([node_id], float(len(open_faults.get(node_id, {}))))
        yield faulty
