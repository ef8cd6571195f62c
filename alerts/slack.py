"""Slack-compatible incoming webhook sink: one readable line per event.

Works with Slack, Mattermost and Rocket.Chat incoming webhooks (``{"text": ...}`` with
``<url|label>`` links). These receivers have no idempotency key, so a retried POST can show
a line twice; the short event id at the end lets a reader see that it is the same event.
"""
from __future__ import annotations

import json

from alerts.config import SlackSinkSettings
from alerts.http_post import fingerprint, http_client, post
from alerts.outbox import OutboxEvent

ICONS = {
    "damage_raised": ":rotating_light:",
    "damage_cleared": ":white_check_mark:",
    "monitoring_blind": ":warning:",
    "monitoring_restored": ":white_check_mark:",
    "node_offline": ":electric_plug:",
    "node_online": ":white_check_mark:",
    "baseline_changed": ":information_source:",
    "sink_disabled": ":warning:",
    "storage_unavailable": ":warning:",
    "sensor_fault": ":warning:",
    "sensor_fault_cleared": ":white_check_mark:",
    "node_decommissioned": ":no_entry_sign:",
    "node_recommissioned": ":arrow_forward:",
    "node_misconfigured": ":warning:",
}


def slack_text(item: OutboxEvent) -> str:
    """One line: icon, the event's summary, links to the measurement and its DI map, event id."""
    payload = item.payload
    parts = [f"{ICONS.get(item.kind, ':bell:')} {_escape(payload.get('summary') or item.kind)}"]
    links = payload.get("links") or {}
    shown = [
        f"<{links[key]}|{label}>"
        for key, label in (("measurement", f"measurement {payload.get('measurement_id')}"), ("di_map_png", "DI map"))
        if key in links
    ]
    if shown:
        parts.append(" ".join(shown))
    parts.append(f"event {str(item.event_id)[:8]}")
    return " | ".join(parts)


def _escape(text: str) -> str:
    # Slack's mrkdwn needs only these three escaped.
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


class SlackTransport:
    """Posts ``{"text": <one line>}`` to the incoming-webhook URL."""

    def __init__(self, settings: SlackSinkSettings) -> None:
        self.settings = settings
        self._client = http_client(settings.timeout_s)

    def endpoint_fingerprint(self) -> str:
        return fingerprint("slack", self.settings.url.get_secret_value())

    def send(self, item: OutboxEvent) -> None:
        body = json.dumps({"text": slack_text(item)}).encode()
        post(self._client, self.settings.url.get_secret_value(), content=body, headers={},
             what=f"slack {self.settings.name}")

    def maintain(self) -> None:
        """Nothing to refresh."""

    def close(self) -> None:
        self._client.close()
