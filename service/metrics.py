"""Prometheus metrics read from the database at scrape time (a custom collector, no global state).

The API's ``/metrics`` is the stored state of the fleet (what the database says); the gateway's
own counters (cycles, retries, delivery attempts) are on its metrics port (gateway/metrics.py).
"""
from __future__ import annotations

import logging
from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Info, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from alerts.metrics import AlertDeliveryCollector, SensorFaultCollector
from db.errors import StorageError
from db.models import MeasurementRow, NodeState
from db.nodes import list_nodes
from db.release import release_labels
from service.database import DatabaseGate

log = logging.getLogger("pipesentry.api")
# A node in these states has no threshold in force: a stored one belongs to the baseline before.
UNTHRESHOLDED_STATES = frozenset({NodeState.COMMISSIONING, NodeState.CALIBRATING})


class FleetCollector(Collector):
    """Per node in service: up, state, DI peak, threshold, last seen/measured, serial counters."""

    def __init__(self, gate: DatabaseGate) -> None:
        self.gate = gate

    def collect(self) -> Iterator[Metric]:
        database_up = GaugeMetricFamily("pipesentry_database_up", "1 if the API could read the database")
        try:
            families = self._read()
        except StorageError as error:
            log.warning("metrics: database unavailable: %s", error)
            database_up.add_metric([], 0)
            yield database_up
            return
        database_up.add_metric([], 1)
        yield database_up
        yield from families

    def _read(self) -> list[Metric]:
        database = self.gate.get()
        labels = ["node"]
        up = GaugeMetricFamily("pipesentry_node_up", "1 if the node answered its last poll", labels=labels)
        state = GaugeMetricFamily(
            "pipesentry_node_state", "1 for the node's current state (one series per state)", labels=["node", "state"]
        )
        peak = GaugeMetricFamily("pipesentry_node_di_peak", "peak damage index of the latest monitor measurement",
                                 labels=labels)
        threshold = GaugeMetricFamily("pipesentry_node_di_threshold",
                                      "the node's damage threshold (absent while it has none: commissioning, calibrating)",
                                      labels=labels)
        seen = GaugeMetricFamily("pipesentry_node_last_seen_timestamp_seconds",
                                 "when the node last answered (absent: never)",
                                 labels=labels)
        measured = GaugeMetricFamily("pipesentry_node_last_measurement_timestamp_seconds",
                                     "acquisition time of the node's last stored measurement", labels=labels)
        errors = CounterMetricFamily("pipesentry_node_link_events",
                                     "serial-link and gateway counters of the node (reset when the node reboots)",
                                     labels=["node", "counter"])
        with database.session() as session:
            # A decommissioned node's series end: no "node down" alert for a node taken out of service.
            nodes = list_nodes(session, include_decommissioned=False)
            # The last stored measurement's time (by id), not the latest timestamp: a clock that stepped
            # forward and back would otherwise show the future-dated one until the clock caught up with it.
            last_ids = select(func.max(MeasurementRow.id)).group_by(MeasurementRow.node_id).scalar_subquery()
            last_measured = dict(
                session.execute(
                    select(MeasurementRow.node_id, MeasurementRow.acquired_at).where(MeasurementRow.id.in_(last_ids))
                ).all()
            )
        for node in nodes:
            name = [node.node_id]
            up.add_metric(name, 1.0 if node.online else 0.0)
            for candidate in NodeState:
                state.add_metric([node.node_id, candidate.value], 1.0 if node.state == candidate else 0.0)
            if node.latest_di_peak is not None:
                peak.add_metric(name, node.latest_di_peak)
            if node.latest_threshold is not None and node.state not in UNTHRESHOLDED_STATES:
                threshold.add_metric(name, node.latest_threshold)
            if node.last_seen_at is not None:  # absent for a node that never answered (up is 0)
                seen.add_metric(name, node.last_seen_at.timestamp())
            if node.node_id in last_measured:
                measured.add_metric(name, last_measured[node.node_id].timestamp())
            for counter, value in sorted((node.error_counters or {}).items()):
                errors.add_metric([node.node_id, str(counter)], float(value))
        return [up, state, peak, threshold, seen, measured, errors]


def metrics_registry(gate: DatabaseGate) -> CollectorRegistry:
    """The fleet's metrics, and alerting's: deliveries per sink (docker/prometheus/alerts.yml alerts on
    them) and each node's faulty receivers; ``pipesentry_build_info``."""
    registry = CollectorRegistry(auto_describe=False)
    Info("pipesentry_build", "the running PipeSentry release", registry=registry).info(release_labels())
    registry.register(FleetCollector(gate))
    registry.register(AlertDeliveryCollector(gate.get))
    registry.register(SensorFaultCollector(gate.get))
    return registry


def exposition(registry: CollectorRegistry) -> bytes:
    return generate_latest(registry)

