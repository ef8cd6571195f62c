"""Chaos: the gateway's wall clock steps back an hour, then forward 400 days, then back to the truth,
while it polls a real mock node (pty) into a real SQLite file (an injected clock: libfaketime does not
work with this Python). What must hold: calibration finishes across the -1 h step; retention prunes
nothing that the real elapsed time would not (+400 d pruned every earlier trace before); "latest", the
lists and the staleness metric follow insertion, not the future-dated record; nothing is lost."""
from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select

from db.database import open_database
from db.measurements import load_traces
from db.models import DetectionRow, MeasurementRow, NodeState
from db.nodes import get_node
from db.queries import latest_detection, measurements_page
from gateway.config import load_settings
from gateway.daemon import Gateway
from service.database import DatabaseGate
from service.metrics import FleetCollector
from tests.support.chaos import Counts, size
from tests.support.clocks import SteppedWallClock
from tests.support.process_harness import (
    gateway_config,
    gateway_node,
    scenario_node,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(300)]  # a mock node process and the gateway's threads

NODE = "clock-a"
FUTURE = timedelta(days=400)


def _state(database) -> NodeState:
    with database.session() as session:
        return get_node(session, NODE).state


def _stored(database) -> int:
    with database.session() as session:
        return int(session.scalar(select(func.count()).select_from(MeasurementRow)) or 0)


def test_clock_steps_both_ways_lose_nothing_and_latest_follows_insertion(tmp_path: Path):
    counts = Counts("clock steps")
    scenario = tmp_path / "s.toml"
    scenario.write_text(scenario_node(NODE, 31))
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path)
    database = None
    gateway = None
    try:
        wait_for_links(links, [NODE], mock)
        db_path = tmp_path / "gateway.db"
        config = tmp_path / "gateway.toml"
        node = gateway_node(NODE, links, interval_s=0.2,
                            threshold={"calibration_count": 5, "hysteresis_count": 2, "false_alarm_rate": 1e-3})
        config.write_text(gateway_config(db_path, [node], retention={"raw_traces_days": 365, "prune_every_s": 0.2}))
        settings = load_settings(config)
        database = open_database(settings.database.url)
        clock = SteppedWallClock()
        gateway = Gateway(settings, database, clock=clock)
        passes = {"n": 0}
        trusted = gateway.retention_clock.now

        def counted_now() -> datetime:
            passes["n"] += 1
            return trusted()

        gateway.retention_clock.now = counted_now  # type: ignore[method-assign]
        gateway.start()

        # -1 h right after the baseline: calibration readings are "older" than the baseline and must count.
        wait_until(lambda: _state(database) == NodeState.CALIBRATING, 120, 0.1, what="calibrating")
        clock.step(timedelta(hours=-1))
        counts.faults += 1
        wait_until(lambda: _state(database) == NodeState.OK, 120, 0.1, what="calibration done after -1 h")

        # +400 d: retention must prune nothing (the traces are minutes old in real time).
        before = _stored(database)
        clock.set_offset(FUTURE)
        counts.faults += 1
        seen = passes["n"]
        extra = size(3, 20)
        wait_until(lambda: _stored(database) >= before + extra and passes["n"] >= seen + 3, 120, 0.1,
                   what="measurements and retention passes after +400 d")

        # Back to the truth: what is stored from now on is the latest, whatever the dates say.
        clock.set_offset(timedelta(0))
        counts.faults += 1
        after_future = _stored(database)
        wait_until(lambda: _stored(database) >= after_future + 2, 120, 0.1, what="measurements after the step back")
        gateway.shutdown(settings.shutdown_timeout_s)
        gateway = None

        now = datetime.now(UTC)
        with database.session() as session:
            rows = session.scalars(select(MeasurementRow).order_by(MeasurementRow.id)).all()
            counts.checked = len(rows)
            counts.lost = sum(1 for r in rows if r.traces_pruned_at is not None)
            keys = [(r.boot_id, r.node_measurement_id) for r in rows]
            counts.duplicated = len(keys) - len(set(keys))
            for row in rows:
                if row.traces_pruned_at is not None:
                    continue  # counted as lost
                try:
                    load_traces(row)
                except Exception:  # noqa: BLE001 (a CorruptBlob or a decoding error: counted, then asserted 0)
                    counts.corrupted += 1
            future = [r for r in rows if r.acquired_at > now + FUTURE / 2]
            assert future, "the +400 d step was not seen by the gateway"
            last = rows[-1]
            assert last.acquired_at <= now  # stored after the clock came back
            assert latest_detection(session, NODE).id == session.scalar(select(func.max(DetectionRow.id)))
            assert measurements_page(session, NODE, limit=1).items[0].id == last.id
        gate = DatabaseGate(settings.database.url, busy_timeout_ms=1000)
        try:
            families = {f.name: f for f in FleetCollector(gate).collect()}
            [sample] = families["pipesentry_node_last_measurement_timestamp_seconds"].samples
            assert sample.value == pytest.approx(last.acquired_at.timestamp())  # not 400 days ahead
        finally:
            gate.dispose()
        counts.report(future_dated=len(future), retention_passes=passes["n"])
        counts.assert_nothing_lost()
    finally:
        if gateway is not None:
            gateway.shutdown(5.0)
        if database is not None:
            database.dispose()
        mock.close()
