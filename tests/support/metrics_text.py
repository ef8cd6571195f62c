"""Reading a Prometheus text exposition (a gateway's /metrics) in tests, with prometheus_client's parser."""
from __future__ import annotations

from prometheus_client.parser import text_string_to_metric_families


def sample(metrics: str, name: str, **labels: str) -> float:
    """The value of the one series named ``name`` with exactly ``labels``."""
    for family in text_string_to_metric_families(metrics):
        for series in family.samples:
            if series.name == name and series.labels == labels:
                return float(series.value)
    raise AssertionError(f"{name}{labels or ''} is not in the gateway's metrics")


def total(metrics: str, name: str, **labels: str) -> float:
    """The sum over the series named ``name`` whose labels include ``labels`` (0 when there is none)."""
    return sum(float(series.value) for family in text_string_to_metric_families(metrics) for series in family.samples
               if series.name == name and labels.items() <= series.labels.items())
