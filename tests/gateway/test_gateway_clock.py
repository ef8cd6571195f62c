"""The gateway's clocks: intervals on the monotonic clock, a wall clock that steps cannot make retention
prune early, and a measurement is dated when the node acquired it, not when the transfer ended."""
from __future__ import annotations

import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import select

from db.database import open_database
from db.models import MeasurementRow
from gateway.clock import ElapsedWall, trusted_now
from gateway.config import NodeSettings
from gateway.node_client import NodeClient
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from mocknode.scenario import NodeScenario
from mocknode.server import MockNodeServer
from tests.support.clocks import SteppedWallClock
from tests.support.process_harness import wait_until

T0 = datetime(2026, 3, 1, tzinfo=UTC)


def test_trusted_now_never_runs_ahead_of_the_elapsed_time():
    assert trusted_now(T0 + timedelta(days=400), T0, elapsed_s=60.0) == T0 + timedelta(seconds=60)
    assert trusted_now(T0 - timedelta(hours=1), T0, elapsed_s=60.0) == T0 - timedelta(hours=1)  # back: prune less
    assert trusted_now(T0 + timedelta(seconds=30), T0, elapsed_s=60.0) == T0 + timedelta(seconds=30)
    assert trusted_now(T0, T0, elapsed_s=-5.0) == T0


def test_elapsed_wall_sees_a_step_and_keeps_to_the_elapsed_time():
    clock = SteppedWallClock()
    elapsed = ElapsedWall(clock)
    clock.step(timedelta(days=400))
    assert elapsed.step_s() > 399 * 86400
    assert elapsed.now() - elapsed.anchor_wall < timedelta(minutes=5)
    clock.set_offset(timedelta(hours=-1))
    assert -3700 < elapsed.step_s() < -3500
    assert elapsed.now() < datetime.now(UTC) - timedelta(minutes=59)


def test_acquired_at_is_when_the_acquire_was_sent_whatever_the_reply_and_the_transfer_take(tmp_path: Path):
    clock = SteppedWallClock()
    sent_at: list[datetime] = []

    class SlowLink(NodeClient):
        """Each ACQUIRE reply and each trace transfer takes a minute of wall-clock time (a stall, retries)."""

        def acquire(self, baseline, timeout_s=None):
            sent_at.append(clock.wall())
            reply = super().acquire(baseline, timeout_s)
            clock.step(timedelta(minutes=1))
            return reply

        def read_traces(self, *args, **kwargs):
            transfer = super().read_traces(*args, **kwargs)
            clock.step(timedelta(minutes=1))
            return transfer

    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    stop = threading.Event()
    with MockNodeServer([NodeScenario(node_id="slow", seed=3)]) as server:
        worker = NodeWorker(NodeSettings(id="slow", url=server.urls["slow"], interval_s=0.05, timeout_s=1.0),
                            db, Heartbeats(), stop, client_factory=SlowLink, clock=clock)
        worker.thread.start()
        try:
            wait_until(lambda: len(_acquired(db)) >= 2, 60, what="two measurements")
        finally:
            stop.set()
            worker.thread.join(10)
    stored = _acquired(db)
    db.dispose()
    # Each within the moment of sending (the wrapper reads the clock just before the command goes out),
    # not the minute the reply took or the two the transfer ended at.
    assert all(abs(at - sent) < timedelta(seconds=30) for at, sent in zip(stored, sent_at, strict=False))


def _acquired(db) -> list[datetime]:
    with db.session() as session:
        return list(session.scalars(select(MeasurementRow.acquired_at).order_by(MeasurementRow.id)))
