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
from db.models import DeliveryStatus, DetectionRow, EventRow, MeasurementRow, NodeRow
from tests.support.alerts_fixtures import deliveries, put_state_events
from tests.support.alerts_receivers import HANG, HttpReceiver
from tests.support.process_harness import (
    PYTHON,
    Proc,
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(150)]  # runs the system's real processes
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
    common = f"secret = \"{SECRET}\"\ntimeout_s = 1.0\nbackoff_base_s = 0.05\nbackoff_cap_s = 0.2\n"
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


def faulty_detections(url: str, rx_index: int) -> tuple[int, int]:
    """(detections stored, of which with ``rx_index`` among their sensor faults)."""
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            faults = session.scalars(select(DetectionRow.sensor_faults)).all()
    finally:
        database.dispose()
    return len(faults), sum(any(f["rx_index"] == rx_index for f in (row or [])) for row in faults)


def sensor_events(url: str) -> list[tuple[str, str]]:
    database = open_database(url, upgrade=False)
    try:
        with database.session() as session:
            rows = session.scalars(select(EventRow).where(EventRow.kind.like("sensor_fault%"))
                                   .order_by(EventRow.created_at)).all()
            return [(r.kind, str(r.id)) for r in rows]
    finally:
        database.dispose()


@pytest.mark.timeout(300)
def test_a_receiver_dying_in_a_real_gateway_is_told_to_the_webhook_once_across_a_restart_and_cleared(tmp_path: Path):
    receiver = HttpReceiver()
    links = tmp_path / "links"
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_node("pipe-1", 11))
    control = tmp_path / "dead-rx"  # while it exists, the mock node's receiver 3 keeps 2 % of its signal
    mock = Proc([PYTHON, str(Path(__file__).resolve().parents[1] / "support" / "mock_on_demand.py"), "--scenario", str(scenario),
                 "--link-dir", str(links)], tmp_path, "mock", env={"PIPESENTRY_TEST_DEAD_RX_FILE": str(control)})
    gateways = []

    def kinds_received(kind: str) -> list[dict]:
        return [r.json()["data"] for r in receiver.accepted() if r.json()["type"] == f"pipesentry.{kind}"]

    try:
        wait_for_links(links, ["pipe-1"], mock)
        db_path = tmp_path / "gateway.db"
        url = f"sqlite:///{db_path}"
        config = tmp_path / "gateway.toml"
        sink = (f"\n[alerting]\npoll_interval_s = 0.1\nsensor_fault_count = 2\n"
                f"\n[[alerting.sinks]]\ntype = \"webhook\"\nname = \"hook\"\nurl = \"{receiver.url}\"\n"
                f"secret = \"{SECRET}\"\ntimeout_s = 2.0\n")
        config.write_text(gateway_config(db_path, [gateway_node("pipe-1", links)]) + sink)
        gateways.append(start_gateway(config, tmp_path, name="gateway0"))
        wait_until(lambda: faulty_detections(url, 3)[0] >= 2, 90, 0.2, what="two healthy monitor measurements")
        assert faulty_detections(url, 3)[1] == 0 and sensor_events(url) == []

        control.write_text("3")
        raised = receiver.wait_for(lambda rs: any(r.status == 200 and r.json()["type"] == "pipesentry.sensor_fault"
                                                  for r in rs), 90, "the sensor_fault at the webhook")
        data = kinds_received("sensor_fault")[0]
        assert data["node_id"] == "pipe-1" and data["receiver"]["rx_index"] == 3
        assert data["receiver"]["kind"] == "no_signal" and data["faulty_receivers"] == [3]
        for request in raised:
            Webhook(SECRET).verify(request.body, request.headers)

        gateways[0].kill()  # a crash while the receiver is still dead
        _total, faulty = faulty_detections(url, 3)
        gateways.append(start_gateway(config, tmp_path, name="gateway1"))
        wait_until(lambda: faulty_detections(url, 3)[1] >= faulty + 3, 90, 0.2,
                   what="three more measurements with receiver 3 faulty after the restart")
        assert [k for k, _ in sensor_events(url)] == ["sensor_fault"], "the restart raised it again"

        control.unlink()
        receiver.wait_for(lambda rs: any(r.status == 200 and r.json()["type"] == "pipesentry.sensor_fault_cleared"
                                         for r in rs), 90, "the sensor_fault_cleared at the webhook")
        cleared = kinds_received("sensor_fault_cleared")[0]
        assert cleared["raised_event_id"] == data["event_id"] and cleared["receiver"] == data["receiver"]
        # At-least-once: the kill may come between the receiver's 200 and its record, so the same
        # event can arrive twice; receivers de-duplicate on its id. One fault, one id.
        assert {d["event_id"] for d in kinds_received("sensor_fault")} == {data["event_id"]}
        assert [k for k, _ in sensor_events(url)] == ["sensor_fault", "sensor_fault_cleared"]
        assert gateways[1].terminate(timeout_s=10) == 0, gateways[1].stderr[-3000:]
    finally:
        for gateway in gateways:
            gateway.close()
        mock.close()
        receiver.close()
