"""docker/prometheus/alerts.yml is a valid Prometheus rule file whose metrics really exist."""
from __future__ import annotations

import re
from pathlib import Path

import yaml
from prometheus_client import CollectorRegistry, generate_latest

from alerts.delivery import SinkWorker
from alerts.metrics import AlertDeliveryCollector
from alerts.webhook import WebhookTransport
from tests.support.alerts_fixtures import alerting, fast_policy, put_state_events
from tests.support.alerts_receivers import GONE, HttpReceiver
from tests.support.db_fixtures import store_sample

RULES = Path(__file__).resolve().parents[2] / "docker" / "prometheus" / "alerts.yml"
NAME = re.compile(r"^[a-zA-Z_:][a-zA-Z0-9_:]*$")
LABEL = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")
DURATION = re.compile(r"^(\d+(ms|s|m|h|d|w|y))+$")
RULE_KEYS = {"alert", "record", "expr", "for", "keep_firing_for", "labels", "annotations"}


def load_rules() -> dict:
    return yaml.safe_load(RULES.read_text())


def test_rule_file_has_the_prometheus_structure():
    doc = load_rules()
    assert set(doc) == {"groups"} and isinstance(doc["groups"], list) and doc["groups"]
    names = [g["name"] for g in doc["groups"]]
    assert len(names) == len(set(names)), "group names must be unique"
    for group in doc["groups"]:
        assert set(group) <= {"name", "interval", "limit", "rules"} and group["rules"]
        for rule in group["rules"]:
            assert set(rule) <= RULE_KEYS, rule
            assert ("alert" in rule) != ("record" in rule)
            assert NAME.match(rule.get("alert") or rule["record"])
            assert isinstance(rule["expr"], str) and rule["expr"].strip()
            if "for" in rule:
                assert DURATION.match(rule["for"]), rule["for"]
            for key in ("labels", "annotations"):
                mapping = rule.get(key, {})
                assert isinstance(mapping, dict)
                assert all(LABEL.match(k) and isinstance(v, str) for k, v in mapping.items()), mapping
            if "alert" in rule:
                assert rule["labels"]["severity"] in {"warning", "critical"}
                assert rule["annotations"]["summary"]


def test_every_metric_the_rules_use_is_exposed(outbox_db, stop):
    # Produce every series the rules use: a measurement, a dead delivery, a sink disabled by 410.
    with outbox_db.write() as session:
        store_sample(session, "node-a")
    gone = HttpReceiver([GONE])
    try:
        settings = alerting({"type": "webhook", "name": "hook", "url": gone.url,
                             "secret": "whsec_" + "QUFB" * 8, **fast_policy()})
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
        sink = settings.sink("hook")
        SinkWorker(settings, sink, WebhookTransport(sink), outbox_db, stop=stop).run_once()
    finally:
        gone.close()
    registry = CollectorRegistry(auto_describe=False)
    registry.register(AlertDeliveryCollector(lambda: outbox_db))
    try:  # the API's own collector, when the API package is present
        from service.metrics import FleetCollector

        class Gate:
            def get(self):
                return outbox_db

        registry.register(FleetCollector(Gate()))
    except ImportError:
        pass
    exposed = generate_latest(registry).decode()
    used = set()
    for group in load_rules()["groups"]:
        for rule in group["rules"]:
            used |= set(re.findall(r"\bpipesentry_[a-z_]+", rule["expr"]))
    assert used, "the rules should watch PipeSentry metrics"
    for metric in sorted(used):
        assert re.search(rf"^{metric}[{{ ]", exposed, re.MULTILINE), f"{metric} is used by a rule but not exposed"
    assert 'pipesentry_alert_sink_deliveries{sink="hook",status="dead"} 1.0' in exposed
