"""The gateway's readiness (``/readyz`` beside its metrics): its loops alive, its uplink keeping up (pure).

Ready means the daemon does its work: every loop's thread runs, and, with an uplink, the
oldest record the centre has not acknowledged is younger than ``[uplink] ready_lag_s``. Not
ready never stops measuring: it tells a load balancer, a supervisor or an operator to look.
"""
from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from typing import Any

from db.uplink_queue import QueueStats
from gateway.uplink.sender import UplinkStats


def readiness_report(
    *,
    dead_loops: Sequence[str],
    now: datetime,
    queue: QueueStats | None = None,
    sender: UplinkStats | None = None,
    ready_lag_s: float | None = None,
) -> tuple[bool, dict[str, Any]]:
    """(ready, the JSON body): the reasons it is not ready, and the uplink's figures when it has one."""
    reasons = [f"loop {name} died (see the log)" for name in dead_loops]
    body: dict[str, Any] = {}
    if queue is not None:
        lag_s = queue.lag_s(now)
        body["uplink"] = {
            "queue_depth": queue.depth,
            "lag_s": round(lag_s, 3),
            "oldest_unsent_at": None if queue.oldest_pending_at is None else queue.oldest_pending_at.isoformat(),
            "refused": queue.refused,
            "last_stored_at": None if sender is None or sender.last_stored_at is None else sender.last_stored_at.isoformat(),
            "last_error": None if sender is None else sender.last_error,
        }
        if ready_lag_s is not None and lag_s > ready_lag_s:
            reasons.append(f"uplink: the oldest unsent record waits {lag_s:.0f} s, more than ready_lag_s "
                           f"{ready_lag_s:g} s" + (f" (last error: {sender.last_error})" if sender and sender.last_error else ""))
    return not reasons, {"status": "not ready" if reasons else "ready", "reasons": reasons, **body}
