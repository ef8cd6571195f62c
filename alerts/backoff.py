"""Alert delivery's retry timing: full-jitter exponential backoff (retry_timing), with the receiver's
Retry-After as a lower bound, itself capped."""
from __future__ import annotations

import random
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime

from retry_timing.backoff import Backoff


def retry_delay_s(
    attempts: int,
    *,
    base_s: float,
    cap_s: float,
    rng: random.Random,
    retry_after_s: float | None = None,
    retry_after_max_s: float = 3600.0,
) -> float:
    """Seconds to wait after the ``attempts``-th failed try (1-based).

    Full jitter (uniform in [0, min(cap, base * 2**(attempts-1))]) spreads retries of many
    deliveries after an outage; a receiver's Retry-After is a lower bound, itself capped.
    """
    delay = Backoff(base_s, cap_s, "full").delay_s(attempts, rng)
    if retry_after_s is not None:
        delay = max(delay, min(max(retry_after_s, 0.0), retry_after_max_s))
    return delay


def parse_retry_after(value: str | None, *, now: datetime | None = None) -> float | None:
    """A Retry-After header (delay-seconds or an HTTP-date) in seconds from now, or None."""
    if value is None:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    now = now or datetime.now(UTC)
    return max(0.0, (when - now).total_seconds())
