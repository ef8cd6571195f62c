"""Alerting inside the real gateway process, against a mock node: kill -9 mid-delivery, a sink down throughout."""
from __future__ import annotations

import base64
import socket
from pathlib import Path

import pytest
from sqlalchemy import func, select
from standardwebhooks.webhooks import Webhook

from alerts.config import AlertingSettings
from db.database import open_database
from db.models import DeliveryStatus, MeasurementRow, NodeRow

from alerts_fixtures import deliveries, put_state_events
from alerts_receivers import HANG, HttpReceiver
from process_harness import gateway_config, start_gateway, start_mock_nodes, wait_for_links, wait_until

pytestmark = pytest.mark.timeout(150)
SECRET = "whsec_" + base64.b64encode(b"g" * 32).decode()
SCENARIO = """
[[nodes]]
node_id = "pipe-1"
seed = 11
[nodes.temperature]
mean_c = 21.0
jitter_c = 0.02
"""


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sinks_toml(receiver_url: str, down_url: str) -> str:
    common = "secret = \"%s\"\ntimeout_s = 1.0\nbackoff_base_s = 0.05\nbackoff_cap_s = 0.2\n" % SECRET
    return (
        # offline_after_s = 5: the watcher looks every 0.5 s (the node answers every 0.3 s).
        "\n[alerting]\npoll_interval_s = 0.1\noffline_after_s = 5\napi_base_url = \"http://127.0.0.1:8000\"\n"
        f"\n[[alerting.sinks]]\ntype = \"webhook\"\nname = \"hook\"\nurl = \"{receiver_url}\"\n{common}"
        f"\n[[alerting.sinks]]\ntype = \"webhook\"\nname = \"down\"\nurl = \"{down_url}\"\nmax_attempts = 3\n{common}"
    )


def measurement_count(url: str) -> int:
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            return int(session.scalar(select(func.count()).select_from(MeasurementRow)))
    finally:
        database.dispose()


def test_gateway_killed_mid_delivery_delivers_after_restart_while_a_down_sink_dies_and_polling_goes_on(tmp_path: Path):
    receiver = HttpReceiver([HANG])
    links = tmp_path / "links"
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(SCENARIO)
    mock = start_mock_nodes(scenario, links, tmp_path)
    gateways = []
    try:
        wait_for_links(links, ["pipe-1"], mock)
        db_path = tmp_path / "gateway.db"
        url = f"sqlite:///{db_path}"
        config = tmp_path / "gateway.toml"
        node = {"id": "pipe-1", "url": str(links / "pipe-1"), "interval_s": 0.3, "timeout_s": 1.0}
        config.write_text(gateway_config(db_path, [node]) + sinks_toml(receiver.url, f"http://127.0.0.1:{closed_port()}/"))
        gateways.append(start_gateway(config, tmp_path, name="gateway0"))
        wait_until(lambda: measurement_count(url) >= 1, 60, 0.2, what="the first measurement stored")

        database = open_database(url, upgrade=False)
        settings = AlertingSettings.model_validate({"sinks": [
            {"type": "webhook", "name": "hook", "url": receiver.url, "secret": SECRET},
            {"type": "webhook", "name": "down", "url": "http://127.0.0.1:9/", "secret": SECRET}]})
        with database.session() as session:
            assert session.get(NodeRow, "pipe-1") is not None
        events = put_state_events(database, settings, node_ids=("pipe-1",),
                                  cycle=[("ok", "suspected"), ("suspected", "damage"), ("damage", "ok")])
        wanted = {str(e.id) for e in events}

        def ours(sink):  # the gateway adds its own events (the commissioning baseline)
            return [d.status for d, e in deliveries(database, sink) if str(e.id) in wanted]

        receiver.wait_for(lambda rs: len(rs) >= 1, 30, "the gateway's first send in flight")
        gateways[0].kill()  # SIGKILL while the receiver holds the request
        assert ours("hook") == [DeliveryStatus.PENDING] * 3

        gateways.append(start_gateway(config, tmp_path, name="gateway1"))
        before = measurement_count(url)
        receiver.wait_for(lambda rs: {r.headers["webhook-id"] for r in rs if r.status == 200} >= wanted, 60,
                          "every event delivered after the restart")
        wait_until(lambda: ours("hook") == [DeliveryStatus.DELIVERED] * 3, 20, 0.1, what="hook deliveries marked delivered")
        wait_until(lambda: ours("down") == [DeliveryStatus.DEAD] * 3, 60, 0.1, what="the down sink's deliveries dead")
        wait_until(lambda: measurement_count(url) > before, 60, 0.2, what="measurements carry on")

        accepted = [r for r in receiver.requests if r.status == 200]
        order = [r.headers["webhook-id"] for r in accepted if r.headers["webhook-id"] in wanted]
        assert order == [str(e.id) for e in events], "per-node order kept across the crash"
        receiver.wait_for(lambda rs: any(r.status == 200 and r.json()["data"]["kind"] == "baseline_changed" for r in rs),
                          30, "the commissioning baseline announced by the gateway")
        for request in receiver.requests:
            Webhook(SECRET).verify(request.body, request.headers)
        assert all(d.attempts == 3 and "ConnectError" in d.last_error
                   for d, e in deliveries(database, "down") if str(e.id) in wanted)
        database.dispose()
        assert gateways[1].terminate(timeout_s=10) == 0, gateways[1].stderr[-3000:]
    finally:
        for gateway in gateways:
            gateway.close()
        mock.close()
        receiver.close()
