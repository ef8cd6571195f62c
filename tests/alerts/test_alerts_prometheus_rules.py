"""docker/prometheus and docker/alertmanager: the shipped rules, their promtool unit tests, the example
configs, and that every series the rules and the Grafana dashboard use is exposed by the API or the gateway."""
from __future__ import annotations

import json
import re
import shutil
import threading
from pathlib import Path

import pytest
import yaml
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from alerts.alertmanager import ALERT_NAMES
from alerts.delivery import SinkWorker
from alerts.webhook import WebhookTransport
from db.database import Database
from db.models import NodeRow, NodeState
from db.nodes import record_node_health
from db.records import StateChangeInput
from gateway.config import NodeSettings
from gateway.metrics import gateway_registry
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from tests.support.alerts_fixtures import alerting, fast_policy, put_state_events
from tests.support.alerts_receivers import GONE, HttpReceiver
from tests.support.api_fixtures import api_metrics_text
from tests.support.db_fixtures import ALARM, store_sample
from tests.support.prometheus_peers import run_tool

DOCKER = Path(__file__).resolve().parents[2] / "docker"
RULES = DOCKER / "prometheus" / "alerts.yml"
RULE_TESTS = DOCKER / "prometheus" / "alerts.test.yml"
PROMETHEUS_CONFIG = DOCKER / "prometheus" / "prometheus.yml"
ALERTMANAGER_CONFIG = DOCKER / "alertmanager" / "alertmanager.yml"
DASHBOARD = DOCKER / "grafana-dashboard.json"
SERIES = re.compile(r"\b(pipesentry_[a-z_]+)")
JOB = re.compile(r'job="([^"]+)"')


def rules() -> list[dict]:
    return [rule for group in yaml.safe_load(RULES.read_text())["groups"] for rule in group["rules"]]


def test_promtool_accepts_the_rules():
    result = run_tool("promtool", "check", "rules", str(RULES))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"SUCCESS: {len(rules())} rules found" in result.stdout


def test_the_rules_unit_tests_pass_under_promtool():
    result = run_tool("promtool", "test", "rules", RULE_TESTS.name, cwd=RULE_TESTS.parent)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "SUCCESS" in result.stdout


def test_every_rule_is_unit_tested_both_firing_and_quiet():
    cases = [case for test in yaml.safe_load(RULE_TESTS.read_text())["tests"] for case in test["alert_rule_test"]]
    for rule in rules():
        mine = [case for case in cases if case["alertname"] == rule["alert"]]
        assert any(case["exp_alerts"] for case in mine), f"{rule['alert']}: no test where it fires"
        assert any(not case["exp_alerts"] for case in mine), f"{rule['alert']}: no test where it stays quiet"


def test_the_silent_node_rule_is_per_node_not_over_the_fleet():
    # The old rule took max() over every node: one silent node among healthy ones never fired it.
    silent = next(rule for rule in rules() if rule["alert"] == "PipeSentryNodeSilent")
    assert "pipesentry_node_interval_seconds" in silent["expr"] and "by (site, node)" in silent["expr"]


def test_the_example_prometheus_config_is_valid_and_scrapes_the_jobs_the_rules_name(tmp_path: Path):
    # promtool also checks the files the config names: the rules, and a key file put in a temp dir.
    key = tmp_path / "pipesentry.key"
    key.write_text("psk_example\n")
    config = PROMETHEUS_CONFIG.read_text().replace("/etc/prometheus/pipesentry.key", str(key))
    (tmp_path / "prometheus.yml").write_text(config)
    shutil.copy(RULES, tmp_path / "alerts.yml")
    result = run_tool("promtool", "check", "config", "prometheus.yml", cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    jobs = {job["job_name"] for job in yaml.safe_load(config)["scrape_configs"]}
    named = {job for rule in rules() for job in JOB.findall(rule["expr"])}
    assert named == {"pipesentry-api", "pipesentry-gateway"} and named <= jobs, (named, jobs)


def test_the_example_alertmanager_config_is_valid_and_inhibits_only_alerts_that_exist():
    result = run_tool("amtool", "check-config", str(ALERTMANAGER_CONFIG))
    assert result.returncode == 0, result.stdout + result.stderr
    known = {rule["alert"] for rule in rules()} | set(ALERT_NAMES)
    config = yaml.safe_load(ALERTMANAGER_CONFIG.read_text())
    for inhibit in config["inhibit_rules"]:
        for matcher in inhibit["source_matchers"] + inhibit["target_matchers"]:
            names = re.fullmatch(r'alertname=~?"([^"]+)"', matcher)
            assert names, matcher
            assert set(names.group(1).split("|")) <= known, matcher


# ------------------------------------------------------------------ every series used is exposed by someone
def exposed_series(text: str) -> set[str]:
    """Sample names of an exposition (counters with their _total)."""
    return {sample.name for family in text_string_to_metric_families(text) for sample in family.samples}


@pytest.fixture
def expositions(outbox_db: Database, stop: threading.Event) -> dict[str, str]:
    """What the API's /metrics and the gateway's metrics port expose over one database in which a
    measurement is stored, a delivery is acknowledged and another sink said 410 Gone (its deliveries dead)."""
    with outbox_db.write() as session:
        before = session.get(NodeRow, "node-a").state
        store_sample(session, "node-a", detection=ALARM, state_change=StateChangeInput(before, NodeState.DAMAGE))
        record_node_health(session, "node-a", online=True, error_counters={"node_crc_errors": 2})
    ok, gone = HttpReceiver(), HttpReceiver([GONE])
    try:
        settings = alerting(
            {"type": "webhook", "name": "hook", "url": ok.url, "secret": "whsec_" + "QUFB" * 8, **fast_policy()},
            {"type": "webhook", "name": "gone", "url": gone.url, "secret": "whsec_" + "QUFB" * 8, **fast_policy()},
        )
        put_state_events(outbox_db, settings, node_ids=("node-a",), cycle=[("ok", "damage")])
        sinks = [SinkWorker(settings, s, WebhookTransport(s), outbox_db, stop=stop) for s in settings.sinks]
        for worker in sinks:
            worker.run_once()
    finally:
        ok.close()
        gone.close()
    node = NodeWorker(NodeSettings(id="node-a", url="loop://", interval_s=60.0), outbox_db, Heartbeats(), stop)
    return {
        "api": api_metrics_text(outbox_db),
        "gateway": generate_latest(gateway_registry([node], sinks, outbox_db)).decode(),
    }


def test_every_series_the_rules_use_is_exposed_by_the_api_or_the_gateway(expositions):
    exposed = exposed_series(expositions["api"]) | exposed_series(expositions["gateway"])
    used = {name for rule in rules() for name in SERIES.findall(rule["expr"])}
    assert used and used <= exposed, f"used by the rules, exposed by nobody: {sorted(used - exposed)}"
    assert 'pipesentry_alert_sink_deliveries{sink="gone",status="dead"} 1.0' in expositions["api"]
    assert 'pipesentry_node_interval_seconds{node="node-a"} 60.0' in expositions["gateway"]


def test_every_series_the_grafana_dashboard_plots_is_exposed_by_the_api_or_the_gateway(expositions):
    dashboard = json.loads(DASHBOARD.read_text())
    expressions = [t["expr"] for panel in dashboard["panels"] for t in panel.get("targets", [])]
    used = {name for expr in expressions for name in SERIES.findall(expr)}
    exposed = exposed_series(expositions["api"]) | exposed_series(expositions["gateway"])
    assert used and used <= exposed, f"plotted, exposed by nobody: {sorted(used - exposed)}"


def test_no_series_is_exposed_by_both_processes(expositions):
    # One fact, one series: a rule on either cannot page twice for it.
    both = exposed_series(expositions["api"]) & exposed_series(expositions["gateway"])
    assert both <= {"pipesentry_build_info"}, sorted(both)


def test_gauges_are_not_named_like_counters_and_counters_end_in_total(expositions):
    for text in expositions.values():
        for family in text_string_to_metric_families(text):
            names = {sample.name for sample in family.samples}
            if family.type == "counter":
                assert all(n.endswith(("_total", "_created")) for n in names), family.name
            else:
                assert not any(n.endswith(("_total", "_count", "_sum", "_bucket")) for n in names), family.name


def test_the_removed_duplicates_are_gone(expositions):
    # pipesentry_node_state{state="damage"} and pipesentry_alert_sink_deliveries{status="dead"} say it.
    api = exposed_series(expositions["api"])
    assert not api & {"pipesentry_node_damage", "pipesentry_alert_deliveries", "pipesentry_alert_deliveries_dead"}


def test_the_scrape_config_in_docs_api_md_is_the_shipped_one():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "api.md").read_text()
    example = yaml.safe_load(doc.split("```yaml\n", 1)[1].split("```", 1)[0])
    shipped = yaml.safe_load(PROMETHEUS_CONFIG.read_text())
    assert example["scrape_configs"] == shipped["scrape_configs"]
