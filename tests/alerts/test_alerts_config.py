"""The [alerting] table of the gateway config: sinks told apart by type, secrets checked, names unique."""
from __future__ import annotations

import base64

import pytest

from alerts.config import AlertingSettings, MqttSinkSettings, SlackSinkSettings, WebhookSinkSettings, webhook_key
from db.models import Severity
from gateway.config import ConfigError, load_settings

SECRET = "whsec_" + base64.b64encode(b"k" * 32).decode()

CONFIG = f"""
[database]
url = "sqlite:///x.db"

[alerting]
api_base_url = "https://pipes.example.org/"
offline_after_s = 300

[[alerting.sinks]]
type = "webhook"
name = "ops-webhook"
url = "https://hooks.example.org/pipesentry"
secret = "{SECRET}"
timeout_s = 3
max_attempts = 12

[[alerting.sinks]]
type = "alertmanager"
name = "am"
url = "http://127.0.0.1:9093"
resend_interval_s = 30

[[alerting.sinks]]
type = "slack"
name = "chat"
url = "https://hooks.slack.com/services/T/B/X"
min_severity = "warning"

[[alerting.sinks]]
type = "mqtt"
name = "scada"
host = "127.0.0.1"
port = 1883

[[nodes]]
id = "node-1"
url = "loop://"
"""


def test_gateway_config_reads_every_sink_type_with_its_policy(tmp_path):
    path = tmp_path / "gateway.toml"
    path.write_text(CONFIG)
    alerting = load_settings(path).alerting
    assert alerting.api_base_url == "https://pipes.example.org"  # trailing slash dropped for links
    assert alerting.offline_after_s == 300
    assert [type(s).__name__ for s in alerting.sinks] == [
        "WebhookSinkSettings", "AlertmanagerSinkSettings", "SlackSinkSettings", "MqttSinkSettings"]
    webhook = alerting.sink("ops-webhook")
    assert isinstance(webhook, WebhookSinkSettings) and webhook.max_attempts == 12 and webhook.timeout_s == 3
    assert webhook_key(webhook.secret) == b"k" * 32
    assert "whsec_" not in repr(webhook)  # secrets never show up in logs or reprs
    assert isinstance(alerting.sink("chat"), SlackSinkSettings) and "hooks.slack.com" not in repr(alerting.sink("chat"))
    assert isinstance(alerting.sink("scada"), MqttSinkSettings)


def test_sinks_receive_events_at_or_above_their_minimum_severity(tmp_path):
    path = tmp_path / "gateway.toml"
    path.write_text(CONFIG)
    alerting = load_settings(path).alerting
    assert alerting.sink_names_for(Severity.INFO) == ("ops-webhook", "am", "scada")
    assert alerting.sink_names_for(Severity.WARNING) == ("ops-webhook", "am", "chat", "scada")


def test_no_alerting_table_means_no_sinks(tmp_path):
    path = tmp_path / "gateway.toml"
    path.write_text('[[nodes]]\nid = "n"\nurl = "loop://"\n')
    assert load_settings(path).alerting.sinks == []


@pytest.mark.parametrize(
    "bad, complaint",
    [
        ('secret = "not-a-whsec"', "whsec_"),
        ('secret = "whsec_%%%"', "base64"),
        ('secret = "whsec_' + base64.b64encode(b"short").decode() + '"', "24 to 64 bytes"),
    ],
)
def test_a_bad_webhook_secret_is_refused_naming_the_key(tmp_path, bad, complaint):
    path = tmp_path / "gateway.toml"
    path.write_text(CONFIG.replace(f'secret = "{SECRET}"', bad))
    with pytest.raises(ConfigError) as error:
        load_settings(path)
    assert "alerting.sinks.0" in str(error.value) and complaint in str(error.value)


def test_unknown_sink_type_and_repeated_names_are_refused():
    with pytest.raises(ValueError, match="type"):
        AlertingSettings.model_validate({"sinks": [{"type": "pager", "name": "p"}]})
    sink = {"type": "mqtt", "name": "same", "host": "127.0.0.1"}
    with pytest.raises(ValueError, match="repeated: same"):
        AlertingSettings.model_validate({"sinks": [sink, sink]})


def test_backoff_cap_below_base_is_refused():
    with pytest.raises(ValueError, match="backoff_cap_s"):
        AlertingSettings.model_validate(
            {"sinks": [{"type": "mqtt", "name": "m", "host": "h", "backoff_base_s": 10, "backoff_cap_s": 1}]})


def test_the_example_in_docs_alerting_md_is_a_valid_config(tmp_path):
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "alerting.md").read_text()
    example = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "gateway.toml"
    path.write_text(example + '\n[[nodes]]\nid = "n"\nurl = "loop://"\n')
    alerting = load_settings(path).alerting
    assert [s.type for s in alerting.sinks] == ["webhook", "alertmanager", "slack", "mqtt"]
