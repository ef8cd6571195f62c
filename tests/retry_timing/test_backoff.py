"""The one backoff: each jitter policy stays in its window, doubles to its cap, and never overflows."""
from __future__ import annotations

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from retry_timing.backoff import Backoff

WINDOWS = {"full": (0.0, 1.0), "equal": (0.5, 1.0), "none": (1.0, 1.0)}  # share of the ceiling


@given(
    attempt=st.integers(0, 10_000),
    base=st.floats(1e-4, 100),
    cap_factor=st.floats(1, 1e6),
    jitter=st.sampled_from(sorted(WINDOWS)),
    seed=st.integers(0, 2**32),
)
def test_every_wait_is_in_its_policy_window_of_the_capped_ceiling(attempt, base, cap_factor, jitter, seed):
    backoff = Backoff(base, base * cap_factor, jitter)
    ceiling = min(base * cap_factor, base * 2.0 ** max(attempt - 1, 0)) if attempt < 1000 else base * cap_factor
    assert backoff.ceiling_s(attempt) == pytest.approx(ceiling)
    low, high = WINDOWS[jitter]
    delay = backoff.delay_s(attempt, random.Random(seed))
    assert low * backoff.ceiling_s(attempt) <= delay <= high * backoff.ceiling_s(attempt)


def test_the_ceiling_doubles_from_the_base_to_the_cap():
    backoff = Backoff(0.5, 60.0, "none")
    assert [backoff.delay_s(n) for n in range(1, 10)] == [0.5, 1, 2, 4, 8, 16, 32, 60, 60]


@pytest.mark.parametrize("jitter, spread", [("full", (0.05, 0.95)), ("equal", (0.52, 0.98))])
def test_jitter_spreads_waits_over_its_whole_window(jitter, spread):
    rng = random.Random(7)
    shares = [Backoff(1.0, 100.0, jitter).delay_s(4, rng) / 8.0 for _ in range(2000)]
    assert min(shares) < spread[0] and max(shares) > spread[1]


@pytest.mark.parametrize("base, cap, jitter", [(0.0, 1.0, "full"), (2.0, 1.0, "equal"), (1.0, 2.0, "some")])
def test_a_backoff_that_cannot_work_is_refused(base, cap, jitter):
    with pytest.raises(ValueError, match=r"base_s|cap_s|jitter"):
        Backoff(base, cap, jitter)
