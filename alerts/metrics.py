"""Prometheus metrics of alert delivery per sink, read from the outbox at scrape time.

For the API's ``/metrics``: ``registry.register(AlertDeliveryCollector(gate.get))``. The
fleet-wide totals (``pipesentry_alert_deliveries{status}``) are the API's own; these add
the per-sink view that ``docker/prometheus/alerts.yml`` alerts on.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from alerts.events import EventKind
from alerts.outbox import delivery_counts, events_of_kind, oldest_pending_age_s
from db.database import Database
from db.errors import StorageError
from db.models import DeliveryStatus

log = logging.getLogger("pipesentry.alerts")

SINK_DELIVERIES = "pipesentry_alert_sink_deliveries"
SINK_OLDEST_PENDING_AGE = "pipesentry_alert_sink_oldest_pending_age_seconds"
SINK_DISABLED = "pipesentry_alert_sink_disabled_timestamp_seconds"


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
