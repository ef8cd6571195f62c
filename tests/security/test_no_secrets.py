"""No secret in any log line, stored error or API answer; no log line an operator's text can forge.

Every sink is configured with a secret (a Slack URL, a webhook secret and a URL with
``user:pass@`` and ``?token=``, an Alertmanager URL with credentials, an MQTT password), real
`pipesentry alerts deliver` delivers to real receivers (each refuses once, so failures are logged
too), and its whole log, the stored deliveries and the API's answers are searched for them.
"""
from __future__ import annotations

import base64
import io
import logging
import sys
import uuid
from pathlib import Path

import httpx
import pytest

from db.database import open_database
from db.log_text import escape_controls, mask_secret, redact
from db.models import DeliveryStatus, NodeRow, NodeState
from db.nodes import upsert_node
from gateway.logs import setup_logging
from service.settings import ApiSettings
from tests.support.alerts_fixtures import alerting, deliveries, put_state_events
from tests.support.alerts_receivers import HttpReceiver, alertmanager_receiver, fail
from tests.support.api_fixtures import (
    DAMAGED_NODE,
    ApiServer,
    copy_database,
    create_test_keys,
    fleet_database,
    free_port,
)
from tests.support.db_fixtures import node_info
from tests.support.mqtt_broker import clear_retained
from tests.support.process_harness import PYTHON, Proc, wait_until

pytestmark = pytest.mark.timeout(180)

SLACK_PATH = "/services/T0SECRET1/B0SECRET2/slackSecretToken123"
WEBHOOK_SECRET = "whsec_" + base64.b64encode(b"webhook-signing-key-32-bytes!!!!").decode()
WEBHOOK_PASSWORD, WEBHOOK_TOKEN = "hookPassw0rd99", "hookQueryToken77"
ALERTMANAGER_PASSWORD = "amPassw0rd42"
MQTT_PASSWORD = "mqttPassw0rd31"
SECRETS = [SLACK_PATH, WEBHOOK_SECRET, WEBHOOK_SECRET.removeprefix("whsec_"), WEBHOOK_PASSWORD, WEBHOOK_TOKEN,
           ALERTMANAGER_PASSWORD, MQTT_PASSWORD, "slackSecretToken123"]


def leaked(text: str) -> list[str]:
    return [secret for secret in SECRETS if secret in text]


def toml_sink(sink: dict) -> str:
    return "\n[[alerting.sinks]]\n" + "".join(
        f"{k} = {v!r}\n".replace("'", '"') if isinstance(v, str) else f"{k} = {v}\n" for k, v in sink.items())


@pytest.mark.e2e
def test_no_sink_secret_reaches_a_log_line_a_stored_error_or_an_api_answer(broker, tmp_path: Path):
    slack, webhook, alertmanager = HttpReceiver([fail(500)]), HttpReceiver([fail(500)]), alertmanager_receiver(
        [fail(500)])
    prefix = f"pipesentry-test/{uuid.uuid4().hex[:8]}/nodes"
    policy = {"timeout_s": 2, "max_attempts": 5, "backoff_base_s": 0.05, "backoff_cap_s": 0.2}
    host_port = lambda receiver: receiver.url.removeprefix("http://")  # noqa: E731
    sinks = [
        {"type": "slack", "name": "chat", "url": slack.url + SLACK_PATH, **policy},
        {"type": "webhook", "name": "hook", "secret": WEBHOOK_SECRET, **policy,
         "url": f"http://ops:{WEBHOOK_PASSWORD}@{host_port(webhook)}/hook?token={WEBHOOK_TOKEN}"},
        {"type": "alertmanager", "name": "am", "url": f"http://am:{ALERTMANAGER_PASSWORD}@{host_port(alertmanager)}",
         **policy},
        {"type": "mqtt", "name": "scada", "host": broker[0], "port": broker[1], "username": "pipesentry",
         "password": MQTT_PASSWORD, "topic_prefix": prefix, "gateway_topic": prefix.replace("/nodes", "/gateway"),
         "timeout_s": 2, "state_interval_s": 0.2},
        # Never reachable (nothing listens on port 9): its error is stored and shown by the API.
        {"type": "slack", "name": "dead", "url": "http://127.0.0.1:9" + SLACK_PATH + "x", "max_attempts": 1,
         "timeout_s": 1},
    ]
    db_path = tmp_path / "alerts.db"
    database = open_database(f"sqlite:///{db_path}")
    settings = alerting(*sinks)
    with database.write() as session:
        upsert_node(session, node_info("pipe-9"))
        session.get(NodeRow, "pipe-9").state = NodeState.OK
    put_state_events(database, settings, node_ids=("pipe-9",), cycle=[("ok", "damage"), ("damage", "ok")])
    config = tmp_path / "gateway.toml"
    config.write_text(f'[database]\nurl = "sqlite:///{db_path}"\n\n[[nodes]]\nid = "pipe-9"\nurl = "loop://"\n\n'
                      '[logging]\nlevel = "DEBUG"\n\n[alerting]\npoll_interval_s = 0.05\n'
                      + "".join(toml_sink(s) for s in sinks))
    deliver = Proc([PYTHON, "-m", "pipesentry", "alerts", "deliver", "--config", str(config), "--no-watch"],
                   tmp_path, "deliver")
    try:
        def settled() -> bool:
            assert deliver.alive(), deliver.stderr[-3000:]
            statuses = {(d.sink, d.status) for d, _ in deliveries(database)}
            return statuses == {(s, DeliveryStatus.DELIVERED) for s in ("chat", "hook", "am", "scada")} | {
                ("dead", DeliveryStatus.DEAD)}

        wait_until(settled, 60, 0.1, what="every sink delivered once it stopped refusing, the dead one given up")
        assert deliver.terminate(timeout_s=15) == 0, deliver.stderr[-3000:]
        log = deliver.stderr
        stored = [d.last_error or "" for d, _ in deliveries(database)]
    finally:
        deliver.close()
        for receiver in (slack, webhook, alertmanager):
            receiver.close()
        clear_retained(f"{prefix}/pipe-9/state", f"{prefix.replace('/nodes', '/gateway')}/status")
        database.dispose()

    assert "try 1/5" in log and "delivered" in log  # the failures and deliveries were logged
    assert any("try 1" in error for error in stored)  # the dead sink's error is stored
    print(f"secrets: {len(SECRETS)} searched for in {len(log.splitlines())} log lines and {len(stored)} stored "
          f"deliveries: {len(leaked(log))} and {len(leaked(' '.join(stored)))} found")
    assert leaked(log) == [], log[-3000:]
    assert leaked(" ".join(stored)) == [], stored

    url = f"sqlite:///{db_path}"
    admin = create_test_keys(url).admin
    with ApiServer(ApiSettings(database_url=url)) as server, httpx.Client(
            base_url=server.base_url, headers={"Authorization": f"Bearer {admin}"}, timeout=10) as client:
        answers = [client.get("/api/v1/alerts").text, client.get("/metrics").text, client.get("/api/v1/keys").text]
    assert leaked(" ".join(answers)) == []


@pytest.mark.e2e
def test_an_operators_reason_cannot_forge_a_line_in_the_api_log(tmp_path_factory, tmp_path: Path):
    path = copy_database(fleet_database(tmp_path_factory.getbasetemp()), tmp_path / "api.db")
    url = f"sqlite:///{path}"
    admin = create_test_keys(url).admin
    port = free_port()
    api = Proc([sys.executable, "-c", "import typer; from pipesentry.commands.api import api; typer.run(api)",
                "--database-url", url, "--port", str(port), "--log-level", "warning"], tmp_path, "api")
    forged = "gone\n2026-12-01 00:00:00 ERROR pipesentry.gateway: FORGED LINE\x1b[2J\x1b[31m"
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until(lambda: httpx.get(f"{base}/readyz", timeout=2).status_code == 200, 30, 0.1, what="api ready")
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {admin}"}, timeout=10) as client:
            answer = client.post(f"/api/v1/nodes/{DAMAGED_NODE}/decommission", json={"reason": forged})
        assert answer.status_code == 200, answer.text
        wait_until(lambda: "decommissioned" in api.stderr, 10, 0.1, what="the decommissioning logged")
    finally:
        api.terminate()
        api.close()
    lines = api.stderr.splitlines()
    [logged] = [line for line in lines if "decommissioned" in line]
    assert "FORGED LINE" in logged and "\\n2026-12-01" in logged  # on the operator's line, escaped
    assert not any(line.startswith("2026-12-01 00:00:00 ERROR") for line in lines)
    assert "\x1b" not in api.stderr


def test_gateway_log_lines_stay_one_line_and_show_no_registered_secret():
    mask_secret("s3cr3t-token-value")
    for json_lines in (False, True):
        stream = io.StringIO()
        setup_logging("INFO", json_lines=json_lines, stream=stream)
        try:
            logging.getLogger("pipesentry.gateway").warning(
                "baseline_changed: re-baselined by alice: %s", "repaired\nFAKE ERROR line\x1b[31m s3cr3t-token-value")
            logging.getLogger("httpx").info("HTTP Request: POST https://hooks.example/services/T/B/X")
        finally:
            logging.getLogger().handlers.clear()
        out = stream.getvalue()
        assert len(out.splitlines()) == 1, out  # httpx's URL line is not written at all
        assert "FAKE ERROR line" in out and "\x1b" not in out and "s3cr3t-token-value" not in out


@pytest.mark.parametrize(("text", "shown"), [
    ("POST https://user:pa55word@am.example:9093/api/v2/alerts failed",
     "POST https://***@am.example:9093/api/v2/alerts failed"),
    ("GET http://hooks.example/hook?token=abc123&x=1 refused", "GET http://hooks.example/hook?*** refused"),
    ("mqtt://u:p@broker:1883", "mqtt://***@broker:1883"),
    ("no url here: a@b", "no url here: a@b"),
])
def test_credentials_in_urls_are_redacted(text, shown):
    assert redact(text) == shown


def test_control_characters_are_escaped_but_text_is_kept():
    assert escape_controls("a\nb\r\x1b[31mc\u2028d\te") == "a\\nb\\r\\x1b[31mc\\u2028d\te"
