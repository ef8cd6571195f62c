"""A retry waits its backoff on the monotonic clock: a wall-clock step back (a bad NTP server, an
RTC reset) does not hold an alert back for the size of the step (issue 15, item 1).

The stored retry time is wall-clock (it must survive a restart); the worker that scheduled a retry
also keeps its deadline on the monotonic clock, and after a restart a stored time further ahead
than any wait the sink ever sets counts as a clock step and is due at once.
"""
from __future__ import annotations

from datetime import timedelta

import pytest

from db.models import DeliveryStatus
from tests.support.alerts_fixtures import T0, alerting, deliveries, fast_policy, put_state_events, sink_worker
from tests.support.alerts_receivers import HttpReceiver, fail

pytestmark = pytest.mark.timeout(60)
SECRET = "whsec_" + "QUJD" * 8
RETRY_AFTER_S = 30  # the receiver's 503 asks for this wait: the retry time is exact, no jitter


class Clocks:
    """The worker's wall clock and monotonic clock, moved by hand."""

    def __init__(self) -> None:
        self.wall = T0 + timedelta(hours=1)
        self.mono = 1000.0

    def advance(self, seconds: float) -> None:
        self.wall += timedelta(seconds=seconds)
        self.mono += seconds


def one_failed_attempt(database, receiver: HttpReceiver, clocks: Clocks, stop):
    settings = alerting({"type": "webhook", "name": "hook", "url": receiver.url, "secret": SECRET,
                         **fast_policy(backoff_base_s=1.0, backoff_cap_s=60.0, retry_after_max_s=120.0)})
    put_state_events(database, settings, node_ids=("node-a",), cycle=[("ok", "suspected")])
    worker = sink_worker(settings, "hook", database, stop, clock=lambda: clocks.wall, monotonic=lambda: clocks.mono)
    worker.run_once()
    ((delivery, _),) = deliveries(database, "hook")
    assert delivery.attempts == 1 and delivery.status == DeliveryStatus.PENDING
    return settings, worker


def test_a_retry_is_not_held_back_by_a_wall_clock_step_back(outbox_db, stop):
    receiver = HttpReceiver([fail(503, **{"Retry-After": str(RETRY_AFTER_S)})])
    clocks = Clocks()
    try:
        _, worker = one_failed_attempt(outbox_db, receiver, clocks, stop)
        clocks.advance(RETRY_AFTER_S - 5)
        worker.run_once()
        assert len(receiver.requests) == 1  # its wait has not passed: not retried early

        clocks.wall -= timedelta(hours=1)  # the wall clock steps back an hour
        clocks.mono += 6  # ... while the retry's 30 s pass on the monotonic clock
        worker.run_once()
        assert [r.status for r in receiver.requests] == [503, 200]
        assert [d.status for d, _ in deliveries(outbox_db, "hook")] == [DeliveryStatus.DELIVERED]
    finally:
        receiver.close()


def test_after_a_restart_a_retry_time_beyond_any_wait_the_sink_sets_is_due_at_once(outbox_db, stop):
    receiver = HttpReceiver([fail(503, **{"Retry-After": str(RETRY_AFTER_S)})])
    clocks = Clocks()
    try:
        settings, _crashed = one_failed_attempt(outbox_db, receiver, clocks, stop)
        restarted = sink_worker(settings, "hook", outbox_db, stop, clock=lambda: clocks.wall,
                                monotonic=lambda: 0.0)  # a new process: its own monotonic clock, no deadlines
        clocks.wall -= timedelta(seconds=restarted.horizon_s() - RETRY_AFTER_S - 5)
        restarted.run_once()
        assert len(receiver.requests) == 1  # still within the longest wait the sink sets: it waits

        clocks.wall -= timedelta(seconds=10)  # now the stored time lies beyond it: the clock went back
        restarted.run_once()
        assert [r.status for r in receiver.requests] == [503, 200]
        assert [d.status for d, _ in deliveries(outbox_db, "hook")] == [DeliveryStatus.DELIVERED]
    finally:
        receiver.close()
