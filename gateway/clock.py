"""The gateway's clocks, injectable: the wall clock (UTC) for what is recorded, the monotonic clock for
every interval it measures (schedules, retention's elapsed time, the integrity check).

A wall clock can step either way (a bad NTP server, an RTC reset): nothing the gateway decides by
elapsed time reads it. :class:`ElapsedWall` is the wall time retention may trust: never later than
the wall clock at the start plus the monotonic time elapsed since, so a step forward prunes nothing
that the real elapsed time would not (docs/gateway.md "Clock steps").
"""
from __future__ import annotations

import time
from datetime import datetime, timedelta
from typing import Protocol

from db.clock import utc_now

STEP_TOLERANCE_S = 60.0  # a wall clock this far from the elapsed time has stepped (NTP slews far less)


class Clock(Protocol):
    def wall(self) -> datetime:
        """Now, timezone-aware UTC (may step)."""
        ...

    def monotonic(self) -> float:
        """Seconds that never go back (only differences mean anything)."""
        ...


class SystemClock:
    """The process' own clocks."""

    def wall(self) -> datetime:
        return utc_now()

    def monotonic(self) -> float:
        return time.monotonic()


def trusted_now(wall: datetime, anchor_wall: datetime, elapsed_s: float) -> datetime:
    """The wall clock, but never later than the anchor plus the real elapsed time (pure)."""
    return min(wall, anchor_wall + timedelta(seconds=max(0.0, elapsed_s)))


class ElapsedWall:
    """Wall time that cannot run ahead of the monotonic clock since it was made."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.anchor_wall = clock.wall()
        self.anchor_mono = clock.monotonic()

    def now(self) -> datetime:
        return trusted_now(self.clock.wall(), self.anchor_wall, self.clock.monotonic() - self.anchor_mono)

    def step_s(self) -> float:
        """How far the wall clock is from the anchor plus the elapsed time (positive: it stepped forward)."""
        expected = self.anchor_wall + timedelta(seconds=self.clock.monotonic() - self.anchor_mono)
        return (self.clock.wall() - expected).total_seconds()
