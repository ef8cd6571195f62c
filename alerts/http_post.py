"""One HTTP POST of an alert with an explicit timeout, its outcome mapped to typed errors.

No retries here: the delivery worker retries (bounded, backoff with jitter) from the
database, so a retry survives a restart. Redirects are not followed (a webhook that moved
must be reconfigured, not silently re-targeted).
"""
from __future__ import annotations

import hashlib

import httpx

from alerts.backoff import parse_retry_after
from alerts.errors import DeliveryFailed, EndpointGone

USER_AGENT = "PipeSentry-Alerts/1"
_BODY_EXCERPT_CHARS = 200


def http_client(timeout_s: float) -> httpx.Client:
    """A client whose connect, read, write and pool waits are each bounded by ``timeout_s``."""
    return httpx.Client(
        timeout=httpx.Timeout(timeout_s),
        follow_redirects=False,
        headers={"User-Agent": USER_AGENT},
        trust_env=False,  # alert receivers are addressed directly, never through an ambient proxy
    )


def post(client: httpx.Client, url: str, *, content: bytes, headers: dict[str, str], what: str) -> httpx.Response:
    """POST ``content``; return the 2xx response or raise DeliveryFailed / EndpointGone."""
    try:
        response = client.post(url, content=content, headers={"Content-Type": "application/json", **headers})
    except httpx.TimeoutException as exc:
        raise DeliveryFailed(f"{what}: timed out ({type(exc).__name__})") from exc
    except httpx.HTTPError as exc:
        raise DeliveryFailed(f"{what}: {type(exc).__name__}: {exc}") from exc
    if response.status_code == 410:
        raise EndpointGone(f"{what}: HTTP 410 Gone", status_code=410)
    if not 200 <= response.status_code < 300:
        excerpt = response.text[:_BODY_EXCERPT_CHARS].replace("\n", " ")
        raise DeliveryFailed(
            f"{what}: HTTP {response.status_code} {excerpt}".rstrip(),
            retry_after_s=parse_retry_after(response.headers.get("Retry-After")),
        )
    return response


def fingerprint(*parts: str) -> str:
    """A short digest naming an endpoint without revealing it (URLs may hold credentials)."""
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()[:16]
