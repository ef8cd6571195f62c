"""Generic webhook sink, signed per Standard Webhooks (https://www.standardwebhooks.com/).

Headers: ``webhook-id`` (the event id: receivers de-duplicate on it), ``webhook-timestamp``
(Unix seconds of this attempt, so the receiver's replay window works on retries) and
``webhook-signature`` = ``v1,<base64 HMAC-SHA256(key, "{id}.{timestamp}.{body}")>`` with the
key from the ``whsec_<base64>`` secret. Body: ``{"type", "timestamp", "data"}``.
"""
from __future__ import annotations

import base64
import hashlib
import hmac
import json
import time
from collections.abc import Callable

from alerts.config import WebhookSinkSettings, webhook_key
from alerts.http_post import fingerprint, http_client, post
from alerts.outbox import OutboxEvent

EVENT_TYPE_PREFIX = "pipesentry."


def signature(key: bytes, msg_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` header value for one message."""
    signed = f"{msg_id}.{timestamp}.".encode() + body
    return "v1," + base64.b64encode(hmac.new(key, signed, hashlib.sha256).digest()).decode()


def webhook_body(item: OutboxEvent) -> bytes:
    """The JSON body: Standard Webhooks' recommended envelope around the event payload."""
    envelope = {"type": EVENT_TYPE_PREFIX + item.kind, "timestamp": item.created_at.isoformat(), "data": item.payload}
    return json.dumps(envelope, separators=(",", ":"), sort_keys=True).encode()


class WebhookTransport:
    """Sends each event as one signed POST."""

    def __init__(self, settings: WebhookSinkSettings, *, clock: Callable[[], float] = time.time) -> None:
        self.settings = settings
        self._key = webhook_key(settings.secret)
        self._clock = clock
        self._client = http_client(settings.timeout_s)

    def endpoint_fingerprint(self) -> str:
        return fingerprint("webhook", self.settings.url)

    def send(self, item: OutboxEvent) -> None:
        body = webhook_body(item)
        msg_id = str(item.event_id)
        timestamp = int(self._clock())
        headers = {
            "webhook-id": msg_id,
            "webhook-timestamp": str(timestamp),
            "webhook-signature": signature(self._key, msg_id, timestamp, body),
        }
        post(self._client, self.settings.url, content=body, headers=headers, what=f"webhook {self.settings.name}")

    def maintain(self) -> None:
        """Nothing to refresh: a webhook receives each event once."""

    def close(self) -> None:
        self._client.close()
