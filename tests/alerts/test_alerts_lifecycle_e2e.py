"""A damage alarm's whole life on real peers: a real gateway polls a mock node whose pipe grows a notch,
raises the alarm to a real Alertmanager 0.25, a Standard Webhooks receiver, a Slack-compatible receiver and
Mosquitto; an operator sets a new baseline through the real API; the alarm ends on every one of them."""
from __future__ import annotations

import base64
import json
import uuid
from pathlib import Path

import httpx
import pytest
from standardwebhooks.webhooks import Webhook

from service.settings import ApiSettings
from tests.support.alerts_receivers import HttpReceiver
from tests.support.api_fixtures import ApiServer, create_test_keys
from tests.support.mqtt_broker import Subscriber, clear_retained
from tests.support.process_harness import (
    PYTHON,
    Proc,
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    wait_for_links,
    wait_until,
)
from tests.support.prometheus_peers import Alertmanager, alertmanager_config

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]
SECRET = "whsec_" + base64.b64encode(b"L" * 32).decode()
NODE = "pipe-1"
MOCK_ON_DEMAND = Path(__file__).resolve().parents[1] / "support" / "mock_on_demand.py"


def sinks_toml(am_url: str, hook_url: str, chat_url: str, prefix: str) -> str:
    policy = "timeout_s = 2.0\nbackoff_base_s = 0.05\nbackoff_cap_s = 0.2\n"
    return (
        '\n[alerting]\npoll_interval_s = 0.1\noffline_after_s = 60\napi_base_url = "http://127.0.0.1:8000"\n'
        f'\n[[alerting.sinks]]\ntype = "alertmanager"\nname = "am"\nurl = "{am_url}"\nresend_interval_s = 2\n{policy}'
        'labels = {site = "test-site"}\n'
        f'\n[[alerting.sinks]]\ntype = "webhook"\nname = "hook"\nurl = "{hook_url}"\nsecret = "{SECRET}"\n{policy}'
        f'\n[[alerting.sinks]]\ntype = "slack"\nname = "chat"\nurl = "{chat_url}"\nmin_severity = "warning"\n{policy}'
        f'\n[[alerting.sinks]]\ntype = "mqtt"\nname = "scada"\nhost = "127.0.0.1"\nport = 1883\n'
        f'topic_prefix = "{prefix}"\ngateway_topic = "{prefix.replace("/nodes", "/gateway")}"\n'
        f"state_interval_s = 0.2\n{policy}"
    )


def webhook_events(receiver: HttpReceiver, kind: str) -> list[dict]:
    found = []
    for request in receiver.accepted():
        Webhook(SECRET).verify(request.body, request.headers)
        body = request.json()
        if body["type"] == f"pipesentry.{kind}":
            found.append(body["data"])
    return found


def damage_alerts(am: Alertmanager) -> list[dict]:
    return [a for a in am.alerts(node=NODE) if a["labels"]["alertname"] == "PipeSentryPipeDamage"]


def notifications(receiver: HttpReceiver, status: str) -> list[dict]:
    """Alertmanager's own webhook notifications of PipeSentryPipeDamage with this status."""
    return [alert for r in receiver.accepted() for alert in r.json()["alerts"]
            if alert["status"] == status and alert["labels"]["alertname"] == "PipeSentryPipeDamage"]


def test_a_damage_alarm_ended_by_a_new_baseline_is_resolved_on_alertmanager_webhook_slack_and_mqtt(broker, tmp_path):
    prefix = f"pstest-{uuid.uuid4().hex[:8]}/nodes"
    state_topic = f"{prefix}/{NODE}/state"
    notified = HttpReceiver()  # Alertmanager's own receiver (send_resolved)
    hook, chat = HttpReceiver(), HttpReceiver()
    am = Alertmanager(tmp_path / "am", alertmanager_config(f"{notified.url}/alertmanager"))
    mqtt_state = Subscriber(state_topic)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_node(NODE, 21, defect=(200.0, 90.0, 0.0)))
    links = tmp_path / "links"
    notch = tmp_path / "notch"  # the paper's notch is in the pipe while this file exists
    mock = Proc([PYTHON, str(MOCK_ON_DEMAND), "--scenario", str(scenario), "--link-dir", str(links)], tmp_path, "mock",
                env={"PIPESENTRY_TEST_DEFECTS_FILE": str(notch)})
    gateway = None
    try:
        wait_for_links(links, [NODE], mock)
        db_path = tmp_path / "gateway.db"
        config = tmp_path / "gateway.toml"
        config.write_text(gateway_config(db_path, [gateway_node(NODE, links)])
                          + sinks_toml(am.url, hook.url, chat.url, prefix))
        gateway = start_gateway(config, tmp_path)
        # commissioning -> calibrating -> ok raise no event; the retained state follows them
        wait_until(lambda: (m := mqtt_state.messages) and json.loads(m[-1].payload)["state"] == "ok", 90,
                   what="the node calibrated (MQTT state ok)")
        notch.write_text("")

        # --- raised: the notch is flagged damage and every sink hears it
        firing = wait_until(lambda: [a for a in damage_alerts(am) if a["labels"]["severity"] == "critical"], 120, 0.3,
                            what="PipeSentryPipeDamage critical active in Alertmanager")
        assert firing[0]["labels"]["site"] == "test-site" and firing[0]["status"]["state"] == "active"
        assert [a["labels"]["alertname"] for a in am.amtool_query(f"node={NODE}")] == ["PipeSentryPipeDamage"]
        raised = wait_until(lambda: [d for d in webhook_events(hook, "damage_raised") if d["state"] == "damage"], 30,
                            what="damage_raised at the webhook")[0]
        wait_until(lambda: any("DAMAGE on node" in r.json()["text"] for r in chat.accepted()), 30, what="Slack line")
        state = wait_until(lambda: (m := mqtt_state.messages) and json.loads(m[-1].payload)["state"] == "damage"
                           and json.loads(m[-1].payload), 30, what="MQTT state damage")
        assert state["alarms"][0]["alarm"] == "damage"
        wait_until(lambda: notifications(notified, "firing"), 30, what="Alertmanager notified the damage")

        # --- an operator sets a new baseline after the repair, through the API
        keys = create_test_keys(f"sqlite:///{db_path}")
        with ApiServer(ApiSettings(database_url=f"sqlite:///{db_path}")) as server, httpx.Client(
            base_url=f"{server.base_url}/api/v1", headers={"Authorization": f"Bearer {keys.operator}"}, timeout=30
        ) as api:
            latest = api.get(f"/nodes/{NODE}/measurements", params={"limit": 1}).json()["items"][0]
            response = api.post(f"/nodes/{NODE}/baselines",
                                json={"measurement_id": latest["id"], "reason": "clamp repaired, new reference"})
            assert response.status_code == 201, response.text

            # --- ended everywhere
            cleared = wait_until(lambda: webhook_events(hook, "damage_cleared"), 60, what="damage_cleared at the webhook")
            assert len({d["event_id"] for d in cleared}) == 1
            end = cleared[0]
            assert end["alarm_id"] == raised["alarm_id"] and end["state"] == "calibrating"
            assert end["ended_by"]["cause"] == "rebaseline" and end["ended_by"]["reason"] == "clamp repaired, new reference"
            assert end["ended_by"]["by"] == "test-operator"
            wait_until(lambda: not damage_alerts(am), 30, 0.3, what="the damage alert resolved in Alertmanager")
            assert am.amtool_query(f"node={NODE}") == []
            resolved = wait_until(lambda: notifications(notified, "resolved"), 30,
                                  what="Alertmanager's resolved notification")
            assert resolved[0]["labels"]["node"] == NODE
            line = wait_until(lambda: [r.json()["text"] for r in chat.accepted() if "cleared" in r.json()["text"]], 30,
                              what="the clearing on Slack")[0]
            assert "new baseline by test-operator: clamp repaired, new reference" in line
            ok = wait_until(lambda: (m := mqtt_state.messages) and json.loads(m[-1].payload)["state"] == "ok"
                            and json.loads(m[-1].payload), 60, what="MQTT retained state ok after recalibrating")
            assert ok["alarms"] == []
        late = Subscriber(state_topic)  # a subscriber connecting now reads the retained state: ok
        try:
            retained = json.loads(late.wait_for(1)[0].payload)
        finally:
            late.close()
        assert retained["state"] == "ok" and retained["alarms"] == []
        # the re-sends (every 2 s) do not bring it back
        wait_until(lambda: httpx.get(f"{am.url}/api/v2/status", timeout=5).status_code == 200, 10, what="am up")
        assert gateway.alive() and not damage_alerts(am)
        assert gateway.terminate(timeout_s=10) == 0, gateway.stderr[-3000:]
    finally:
        if gateway is not None:
            gateway.close()
        mock.close()
        mqtt_state.close()
        am.close()
        for receiver in (notified, hook, chat):
            receiver.close()
        clear_retained(state_topic, f"{prefix.replace('/nodes', '/gateway')}/status")
