"""A clock a test advances itself (for the mock node's injectable clock), instead of sleeping."""
from __future__ import annotations

import threading


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
