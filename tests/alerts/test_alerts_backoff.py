"""Retry timing: full-jitter exponential backoff within its bounds; Retry-After as a capped lower bound."""
from __future__ import annotations

import random
from datetime import UTC, datetime

from hypothesis import given
from hypothesis import strategies as st

from alerts.backoff import parse_retry_after, retry_delay_s


@given(
    attempts=st.integers(1, 500),
    base=st.floats(0.001, 100),
    cap_factor=st.floats(1, 1000),
    seed=st.integers(0, 2**32),
    retry_after=st.none() | st.floats(0, 1e6),
)
def test_delay_is_within_the_full_jitter_window_or_the_capped_retry_after(attempts, base, cap_factor, seed, retry_after):
    cap = base * cap_factor
    delay = retry_delay_s(attempts, base_s=base, cap_s=cap, rng=random.Random(seed), retry_after_s=retry_after,
                          retry_after_max_s=3600)
    window = min(cap, base * 2.0 ** (attempts - 1))
    floor = 0.0 if retry_after is None else min(retry_after, 3600)
    assert floor <= delay <= max(window, floor)


def test_jitter_spreads_retries_over_the_whole_window():
    rng = random.Random(1)
    delays = [retry_delay_s(4, base_s=1.0, cap_s=100.0, rng=rng) for _ in range(2000)]
    assert min(delays) < 0.5 and max(delays) > 7.5 and all(0 <= d <= 8 for d in delays)


def test_retry_after_as_seconds_or_http_date_and_garbage_ignored():
    now = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
    assert parse_retry_after("120") == 120.0
    assert parse_retry_after("Sun, 01 Mar 2026 12:01:30 GMT", now=now) == 90.0
    assert parse_retry_after("Sun, 01 Mar 2026 11:00:00 GMT", now=now) == 0.0
    assert parse_retry_after("soon") is None and parse_retry_after(None) is None
