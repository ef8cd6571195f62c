"""The gateway's own metrics: served by the real daemon on its [metrics] port, and what they count."""
from __future__ import annotations

import base64
import logging
import socket
from pathlib import Path

import httpx
import pytest
from prometheus_client import CollectorRegistry
from prometheus_client.parser import text_string_to_metric_families

from gateway.config import MetricsSettings, load_settings
from gateway.metrics import serve_metrics
from tests.support.alerts_receivers import HttpReceiver, fail
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

SECRET = "whsec_" + base64.b64encode(b"m" * 32).decode()


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """{(sample name, sorted labels): value} of an exposition."""
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def value(scrape: dict, name: str, **labels: str) -> float | None:
    return scrape.get((name, tuple(sorted(labels.items()))))


@pytest.mark.e2e
@pytest.mark.timeout(150)
def test_the_gateway_counts_cycles_retries_failures_and_deliveries_on_its_metrics_port(tmp_path: Path):
    # pipe-1 answers over a link that flips a bit now and then (retries); pipe-2's port never appears.
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_node("pipe-1", 7))
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path, "--corrupt-byte-rate", "2e-5")
    receiver = HttpReceiver([fail(500)])  # the first delivery fails, its retry is acknowledged
    gateway = None
    try:
        wait_for_links(links, ["pipe-1"], mock)
        config = tmp_path / "gateway.toml"
        nodes = [gateway_node("pipe-1", links, interval_s=0.3), gateway_node("pipe-2", links, interval_s=45.0)]
        sink = (f'\n[alerting]\npoll_interval_s = 0.1\noffline_after_s = 5\n\n[[alerting.sinks]]\ntype = "webhook"\nname = "hook"\n'
                f'url = "{receiver.url}"\nsecret = "{SECRET}"\nbackoff_base_s = 0.05\nbackoff_cap_s = 0.1\n')
        config.write_text(gateway_config(tmp_path / "gateway.db", nodes) + sink)
        gateway = start_gateway(config, tmp_path)
        port = gateway_metrics_port(gateway)

        def scrape() -> dict:
            response = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5)
            assert response.status_code == 200, response.text
            return samples(response.text)

        def settled(s: dict) -> bool:
            return ((value(s, "pipesentry_gateway_node_cycles_total", node="pipe-1") or 0) >= 6
                    and (value(s, "pipesentry_gateway_node_retries_total", node="pipe-1") or 0) >= 1
                    and value(s, "pipesentry_gateway_alert_last_delivery_timestamp_seconds", sink="hook") is not None)

        first = wait_until(lambda: (s := scrape()) and settled(s) and s, 90, 0.5,
                           what="cycles, a retry and a delivery counted")
        assert value(first, "pipesentry_node_interval_seconds", node="pipe-1") == 0.3
        assert value(first, "pipesentry_node_interval_seconds", node="pipe-2") == 45.0
        # pipe-1's ring has not drifted (the mock's gain is steady); pipe-2 has imaged nothing
        assert value(first, "pipesentry_node_baseline_gain", node="pipe-1") == pytest.approx(1.0, abs=0.02)
        assert abs(value(first, "pipesentry_node_baseline_stretch", node="pipe-1")) < 1e-3
        # the mock node reports the pipe's own temperature: its thermometer and the wave agree
        assert abs(value(first, "pipesentry_node_thermometer_offset_celsius", node="pipe-1")) < 1.0
        assert value(first, "pipesentry_node_thermometer_offset_celsius", node="pipe-2") is None
        assert value(first, "pipesentry_node_baseline_gain", node="pipe-2") is None
        assert (value(first, "pipesentry_gateway_node_cycle_failures_total", node="pipe-2", reason="port") or 0) >= 1
        assert value(first, "pipesentry_gateway_node_cycles_total", node="pipe-2") == 0
        assert value(first, "pipesentry_gateway_alert_attempts_total", sink="hook") >= 2
        assert value(first, "pipesentry_gateway_alert_failures_total", sink="hook") >= 1
        assert any(name == "pipesentry_build_info" and dict(labels)["version"] for name, labels in first)
        assert value(first, "process_start_time_seconds") is not None
        # Counters only go up while the gateway runs.
        later = wait_until(
            lambda: (s := scrape()) and s[("pipesentry_gateway_node_cycles_total", (("node", "pipe-1"),))]
            > first[("pipesentry_gateway_node_cycles_total", (("node", "pipe-1"),))] and s, 30, 0.3, what="more cycles")
        for key, counted in first.items():
            if key[0].endswith("_total") and key in later:
                assert later[key] >= counted, key
        assert wait_until(lambda: value(scrape(), "pipesentry_gateway_alert_queue_depth", sink="hook") == 0, 30,
                          what="the outbox drained")
        assert gateway.terminate(timeout_s=10) == 0, gateway.stderr[-3000:]
        with pytest.raises(httpx.TransportError):
            httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=2)  # stopped with the gateway
    finally:
        if gateway is not None:
            gateway.close()
        mock.close()
        receiver.close()


def test_a_taken_metrics_port_is_logged_and_the_gateway_goes_on_without_it(caplog):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with caplog.at_level(logging.ERROR, logger="pipesentry.gateway"):
            served = serve_metrics(MetricsSettings(port=port), CollectorRegistry())
    assert served is None
    assert f"metrics not served: cannot listen on 127.0.0.1:{port}" in caplog.text


def test_metrics_switched_off_open_no_port():
    assert serve_metrics(MetricsSettings(enabled=False), CollectorRegistry()) is None


def test_port_zero_serves_on_a_free_port_until_closed():
    served = serve_metrics(MetricsSettings(port=0), CollectorRegistry())
    assert served is not None and served.port > 0
    try:
        assert httpx.get(f"http://127.0.0.1:{served.port}/metrics", timeout=5).status_code == 200
    finally:
        served.close()
    with pytest.raises(httpx.ConnectError):
        httpx.get(f"http://127.0.0.1:{served.port}/metrics", timeout=2)


def test_the_example_in_docs_gateway_md_is_a_valid_config(tmp_path: Path):
    doc = (Path(__file__).resolve().parents[2] / "docs" / "gateway.md").read_text()
    example = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "gateway.toml"
    # --check requires the SQLite file's directory: the systemd unit's StateDirectory, created by systemd.
    path.write_text(example.replace("/var/lib/pipesentry", str(tmp_path)))
    settings = load_settings(path)
    assert settings.metrics == MetricsSettings(enabled=True, host="127.0.0.1", port=9646)
    assert settings.nodes[0].interval_s == 60
