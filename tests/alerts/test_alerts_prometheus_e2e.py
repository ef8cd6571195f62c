"""The shipped prometheus.yml and alerts.yml in a real Prometheus 2.42 that scrapes a real gateway's metrics port
and the real API's /metrics (with a viewer key): both jobs up, the rules evaluate without error, nothing fires for
a healthy node, and every Grafana panel's query is valid PromQL that finds series."""
from __future__ import annotations

import json
import shutil
import time
from datetime import datetime
from pathlib import Path

import pytest
import yaml

from service.settings import ApiSettings
from tests.support.alerts_receivers import HttpReceiver
from tests.support.api_fixtures import ApiServer, create_test_keys
from tests.support.process_harness import (
    gateway_config,
    gateway_metrics_port,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)
from tests.support.prometheus_peers import Prometheus

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(180)]
DOCKER = Path(__file__).resolve().parents[2] / "docker"
NODE = "pipe-1"


def shipped_config_for(api_port: int, gateway_port: int, key_file: Path) -> dict:
    """docker/prometheus/prometheus.yml with this test's targets and key file, scraping every second."""
    config = yaml.safe_load((DOCKER / "prometheus" / "prometheus.yml").read_text())
    config["global"] = {"scrape_interval": "1s", "evaluation_interval": "1s"}
    config.pop("alerting")  # no Alertmanager here: the rules are evaluated, not sent
    targets = {"pipesentry-api": api_port, "pipesentry-gateway": gateway_port}
    for job in config["scrape_configs"]:
        job["static_configs"][0]["targets"] = [f"127.0.0.1:{targets[job['job_name']]}"]
        if "authorization" in job:
            job["authorization"]["credentials_file"] = str(key_file)
    return config


def test_a_real_prometheus_scrapes_both_jobs_of_the_shipped_config_and_evaluates_every_rule(tmp_path: Path):
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_node(NODE, 5))
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path)
    receiver = HttpReceiver()
    gateway = None
    try:
        wait_for_links(links, [NODE], mock)
        db_path = tmp_path / "gateway.db"
        sink = (f'\n[alerting]\npoll_interval_s = 0.1\noffline_after_s = 5\n\n[[alerting.sinks]]\ntype = "webhook"\n'
                f'name = "hook"\nurl = "{receiver.url}"\nsecret = "whsec_{"QUJD" * 8}"\n')
        (tmp_path / "gateway.toml").write_text(gateway_config(db_path, [gateway_node(NODE, links)]) + sink)
        gateway = start_gateway(tmp_path / "gateway.toml", tmp_path)
        gateway_port = gateway_metrics_port(gateway)
        wait_until(lambda: "measurement 3 stored" in gateway.stderr and receiver.accepted(), 60,
                   what="a few measurements and a delivery (baseline_changed)")
        keys = create_test_keys(f"sqlite:///{db_path}")
        key_file = tmp_path / "pipesentry.key"
        key_file.write_text(keys.viewer + "\n")
        with ApiServer(ApiSettings(database_url=f"sqlite:///{db_path}")) as api:
            work = tmp_path / "prometheus"
            work.mkdir()
            config = work / "prometheus.yml"
            config.write_text(yaml.safe_dump(shipped_config_for(api.port, gateway_port, key_file), sort_keys=False))
            shutil.copy(DOCKER / "prometheus" / "alerts.yml", work / "alerts.yml")
            with Prometheus(work, config) as prometheus:
                def jobs_up() -> dict[str, str]:
                    targets = prometheus.api("targets")["activeTargets"]
                    return {t["labels"]["job"]: t["health"] for t in targets}

                health = wait_until(lambda: (h := jobs_up()) and set(h.values()) == {"up"} and h, 60, 0.5,
                                    what="both jobs scraped")
                assert set(health) == {"pipesentry-api", "pipesentry-gateway"}
                # The per-node staleness rule joins the two jobs on (site, node).
                wait_until(lambda: prometheus.query("pipesentry_node_interval_seconds"), 30, 0.5, what="intervals")
                (interval,) = prometheus.query("pipesentry_node_interval_seconds")
                assert interval["metric"]["node"] == NODE and interval["metric"]["site"] == "site-1"
                assert interval["metric"]["job"] == "pipesentry-gateway" and float(interval["value"][1]) == 0.3
                (last,) = prometheus.query("pipesentry_node_last_measurement_timestamp_seconds")
                assert last["metric"]["job"] == "pipesentry-api" and last["metric"]["node"] == NODE
                silent = next(r["expr"] for g in yaml.safe_load((work / "alerts.yml").read_text())["groups"]
                              for r in g["rules"] if r["alert"] == "PipeSentryNodeSilent")
                threshold = prometheus.query(silent.split(">", 1)[1].strip().removeprefix("on (site, node)").strip())
                assert [float(t["value"][1]) for t in threshold] == [pytest.approx(3 * 0.3 + 600)]
                assert prometheus.query(silent) == []  # measured a moment ago: not silent

                # A rule evaluated before the first scrape sees no `up` series (absent() is true) and
                # stays pending until its next evaluation: judge only evaluations made after both jobs
                # were up, one evaluation interval (1 s) later so the scrape's samples are in.
                settled_after = time.time() + 1.0

                def evaluated() -> list[dict]:
                    groups = prometheus.api("rules")["groups"]
                    rules = [r for g in groups for r in g["rules"]]
                    done = all(r.get("lastEvaluation", "").startswith("20")
                               and datetime.fromisoformat(r["lastEvaluation"]).timestamp() > settled_after
                               for r in rules)
                    return rules if done else []

                rules = wait_until(evaluated, 30, 0.5, what="every rule evaluated after both jobs were up")
                assert len(rules) == 8
                assert all(r["health"] == "ok" and not r.get("lastError") for r in rules), rules
                assert [r["name"] for r in rules if r["state"] != "inactive"] == []
                # Every Grafana panel's query is valid and finds series (the $node variable: every node).
                # A rate or increase needs two samples of a series: a counter that appeared in the last
                # scrape finds nothing until the next one (1 s here), so each query gets a few scrapes.
                dashboard = json.loads((DOCKER / "grafana-dashboard.json").read_text())
                for panel in dashboard["panels"]:
                    for target in panel.get("targets", []):
                        expr = target["expr"].replace("$node", ".*")
                        wait_until(lambda expr=expr: prometheus.query(expr), 10, 0.5,
                                   what=f"{panel['title']}: {expr} to find series")
        assert gateway.terminate(timeout_s=10) == 0, gateway.stderr[-3000:]
    finally:
        if gateway is not None:
            gateway.close()
        mock.close()
        receiver.close()
