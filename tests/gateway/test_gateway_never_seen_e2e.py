"""A configured node that never answers is seen: the real gateway process registers it at its start,
its metrics show it, the API lists it as never seen, and node_offline reaches a real webhook receiver;
when a node finally answers on that port, node_online follows and its row fills in from INFO.

The port is a real pseudo-terminal nobody answers on (tests/support/silent_port.py); then the mock
node process serves that same path. Every wait is bounded.
"""
from __future__ import annotations

import base64
import re
from pathlib import Path

import httpx
import pytest

from db.database import open_database
from db.models import NodeRow
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
from tests.support.silent_port import SilentPty

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]
SECRET = "whsec_" + base64.b64encode(b"s" * 32).decode()
NODE = "node-s"


def alerting_toml(receiver_url: str) -> str:
    # offline_after_s = 3: the watcher looks every 0.5 s.
    return (
        "\n[alerting]\npoll_interval_s = 0.1\noffline_after_s = 3\napi_base_url = \"http://127.0.0.1:8000\"\n"
        f"\n[[alerting.sinks]]\ntype = \"webhook\"\nname = \"hook\"\nurl = \"{receiver_url}\"\nsecret = \"{SECRET}\"\n"
        "timeout_s = 1.0\nbackoff_base_s = 0.05\nbackoff_cap_s = 0.2\n"
    )


def stored_node(url: str) -> NodeRow | None:
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            node = session.get(NodeRow, NODE)
            if node is not None:
                session.expunge(node)
            return node
    finally:
        database.dispose()


def kinds(requests) -> list[str]:
    return [r.json()["data"]["kind"] for r in requests if r.status == 200]


def of_kind(requests, kind: str) -> list[dict]:
    return [r.json()["data"] for r in requests if r.status == 200 and r.json()["data"]["kind"] == kind]


def metric(text: str, name: str, **labels: str) -> float | None:
    wanted = ",".join(f'{k}="{v}"' for k, v in labels.items())
    found = re.search(rf"^{re.escape(name)}\{{{re.escape(wanted)}\}} (\S+)$", text, re.MULTILINE)
    return None if found is None else float(found.group(1))


def test_a_node_that_never_answers_is_listed_counted_and_reported_offline_until_its_first_answer(tmp_path: Path):
    links = tmp_path / "links"
    db_path = tmp_path / "gateway.db"
    url = f"sqlite:///{db_path}"
    receiver = HttpReceiver()
    silent = SilentPty(links / NODE)
    config = tmp_path / "gateway.toml"
    node = gateway_node(NODE, links, timeout_s=0.3, interval_s=0.3)
    config.write_text(gateway_config(db_path, [node], reopen_backoff_max_s=1.0) + alerting_toml(receiver.url))
    gateway = start_gateway(config, tmp_path)
    mock = None
    try:
        # At once: the node has its row, never seen, with nothing INFO would tell.
        registered = wait_until(lambda: stored_node(url), 20, 0.1, what="the configured node's row")
        assert registered.never_seen and registered.online is False and registered.first_seen_at is None
        assert (registered.n_channels, registered.geometry, registered.firmware) == (None, None, None)

        # The gateway's metrics: its cycles on the silent port fail (the node does not answer INFO).
        port = gateway_metrics_port(gateway)

        def failures() -> float:
            text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
            return metric(text, "pipesentry_gateway_node_cycle_failures_total", node=NODE, reason="node") or 0.0

        wait_until(lambda: failures() >= 1, 20, 0.2, what="a failed cycle counted in the gateway's metrics")

        # node_offline, saying it was never seen, at a real webhook receiver.
        receiver.wait_for(lambda rs: "node_offline" in kinds(rs), 30, "node_offline delivered")
        offline, = of_kind(receiver.requests, "node_offline")
        assert offline["node_id"] == NODE and offline["never_seen"] is True and offline["online"] is False
        assert offline["last_seen_at"] == registered.watched_since.isoformat()
        assert "never answered" in offline["summary"]

        # The API lists it as never seen, offline, geometry unknown; its /metrics say down.
        keys = create_test_keys(url)
        with ApiServer(ApiSettings(database_url=url)) as api:
            client = httpx.Client(base_url=api.base_url, headers={"Authorization": f"Bearer {keys.viewer}"}, timeout=10)
            listed = {n["node_id"]: n for n in client.get("/api/v1/nodes").json()}
            assert set(listed) == {NODE}
            view = listed[NODE]
            assert view["health"]["never_seen"] is True and view["health"]["online"] is False
            assert view["health"]["last_seen_at"] is None and view["health"]["first_seen_at"] is None
            assert view["geometry"] is None and view["n_channels"] is None and view["state"] == "commissioning"
            assert view["error_counters"]["gateway_failures"] >= 1  # stored with its row
            api_metrics = client.get("/metrics").text
            assert metric(api_metrics, "pipesentry_node_up", node=NODE) == 0.0
            assert metric(api_metrics, "pipesentry_node_last_seen_timestamp_seconds", node=NODE) is None
            client.close()

        # The node answers at last, on the same path: node_online says it is its first answer.
        silent.close()
        scenario = tmp_path / "scenario.toml"
        scenario.write_text(scenario_node(NODE, seed=5))
        mock = start_mock_nodes(scenario, links, tmp_path)
        wait_for_links(links, [NODE], mock)
        receiver.wait_for(lambda rs: "node_online" in kinds(rs), 30, "node_online delivered")
        online, = of_kind(receiver.requests, "node_online")
        assert online["first_seen"] is True and online["offline_event_id"] == offline["event_id"]
        assert online["alarm_id"] == offline["alarm_id"] and online["online"] is True
        seen = stored_node(url)
        assert seen is not None and not seen.never_seen and seen.n_channels == 16 and seen.firmware  # the mock pipe: 16 receivers
        assert seen.geometry is not None and seen.watched_since == registered.watched_since
        assert seen.first_seen_at is not None and seen.first_seen_at > seen.watched_since
        assert len(of_kind(receiver.requests, "node_offline")) == 1
        assert gateway.terminate(timeout_s=15) == 0, gateway.stderr[-3000:]
        assert "Traceback" not in gateway.stderr
    finally:
        silent.close()
        gateway.close()
        if mock is not None:
            mock.close()
        receiver.close()
