"""Clocks a test moves itself: the mock node's monotonic clock (instead of sleeping), and the gateway's
wall clock stepped as a bad NTP server steps it."""
from __future__ import annotations

import threading
import time
from datetime import UTC, datetime, timedelta


class ManualClock:
    """Monotonic seconds that move only when ``advance`` is called; safe to read from other threads."""

    def __init__(self, start_s: float = 1000.0) -> None:
        self._now_s = start_s
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._now_s

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"a monotonic clock does not go back ({seconds} s)")
        with self._lock:
            self._now_s += seconds


class SteppedWallClock:
    """The gateway's clocks (gateway.clock.Clock) with a wall clock the test steps either way, as a bad NTP
    server or an RTC reset does; the monotonic clock is the real one (the elapsed time does not step)."""

    def __init__(self) -> None:
        self._offset = timedelta(0)
        self._lock = threading.Lock()

    def wall(self) -> datetime:
        with self._lock:
            return datetime.now(UTC) + self._offset

    def monotonic(self) -> float:
        return time.monotonic()

    def step(self, by: timedelta) -> None:
        with self._lock:
            self._offset += by

    def set_offset(self, offset: timedelta) -> None:
        with self._lock:
            self._offset = offset
