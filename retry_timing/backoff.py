"""Exponential backoff, capped, with one of three jitter policies (pure; the caller sleeps or schedules).

Try n (1-based) may wait up to ``min(cap_s, base_s * 2**(n-1))``, the *ceiling*; the policy
draws the wait from it:

- ``full``: uniform in [0, ceiling] — spreads many clients retrying after one outage (the
  alert sinks: hundreds of deliveries waiting on one receiver);
- ``equal``: uniform in [ceiling/2, ceiling] — never near zero, so a retried command always
  leaves the other side time to finish what it is doing (the node's commands);
- ``none``: the ceiling itself — for a resource only this caller uses (reopening its own port).

Each use names its policy where it builds its ``Backoff`` (docs/architecture.md lists them).
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Literal

Jitter = Literal["full", "equal", "none"]
_MAX_EXPONENT = 62  # 2**62 x any base is past every cap; keeps the arithmetic finite
_SHARED_RNG = random.Random()


@dataclass(frozen=True)
class Backoff:
    """Waits between tries: ``base_s`` doubling per try up to ``cap_s``, drawn per ``jitter``."""

    base_s: float
    cap_s: float
    jitter: Jitter

    def __post_init__(self) -> None:
        if not self.base_s > 0:
            raise ValueError(f"base_s must be positive, got {self.base_s}")
        if not self.cap_s >= self.base_s:
            raise ValueError(f"cap_s ({self.cap_s}) must be at least base_s ({self.base_s})")
        if self.jitter not in ("full", "equal", "none"):
            raise ValueError(f"jitter must be full, equal or none, got {self.jitter!r}")

    def ceiling_s(self, attempt: int) -> float:
        """The longest wait after the ``attempt``-th failed try (1-based; 0 counts as 1)."""
        exponent = min(max(attempt - 1, 0), _MAX_EXPONENT)
        return min(self.cap_s, self.base_s * 2.0**exponent)

    def delay_s(self, attempt: int, rng: random.Random | None = None) -> float:
        """The wait after the ``attempt``-th failed try, drawn from ``rng`` (default: the module's) per the
        jitter policy."""
        ceiling = self.ceiling_s(attempt)
        rng = rng or _SHARED_RNG
        if self.jitter == "full":
            return rng.uniform(0.0, ceiling)
        if self.jitter == "equal":
            return rng.uniform(0.5 * ceiling, ceiling)
        return ceiling
