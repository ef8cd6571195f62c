"""Chaos: kill -9 of the gateway (a real process) at random moments, in a bounded loop: during its
first migration, while it acquires, right after a store, and while it delivers an alert. What must
hold after every kill: integrity_check ok, every measurement committed before the kill still there
and unchanged (only the one in flight at the kill may be missing), none half-written or duplicated,
and every outbox event delivered at least once (receivers de-duplicate on webhook-id)."""
from __future__ import annotations

import base64
import hashlib
import random
import sqlite3
import time
import uuid
from pathlib import Path

import pytest

from tests.support.alerts_receivers import HttpReceiver
from tests.support.chaos import Counts, size
from tests.support.process_harness import (
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(600)]  # mock nodes and the gateway as real processes

NODES = ["kill-a", "kill-b"]
MOMENTS = ("delivery", "storage", "acquisition")  # reduced: delivery only (tests/gateway kills during stores)
SECRET = "whsec_" + base64.b64encode(bytes(range(32))).decode()


def _snapshot(db_path: Path) -> dict[int, tuple]:
    """Every committed measurement as (boot, node's number, kind, sha256 of its traces)."""
    if not db_path.exists():
        return {}
    with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True) as connection:
        tables = {r[0] for r in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "measurements" not in tables:
            return {}
        rows = connection.execute("SELECT id, node_id, boot_id, node_measurement_id, kind, traces_blob "
                                  "FROM measurements").fetchall()
    return {r[0]: (r[1], r[2], r[3], r[4], None if r[5] is None else hashlib.sha256(r[5]).hexdigest()) for r in rows}


def _integrity(db_path: Path) -> str:
    if not db_path.exists():
        return "ok"
    with sqlite3.connect(db_path) as connection:
        return connection.execute("PRAGMA integrity_check").fetchone()[0]


def _event_ids(db_path: Path) -> set[uuid.UUID]:
    with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True) as connection:
        return {uuid.UUID(r[0]) for r in connection.execute("SELECT id FROM events")}


def _delivered_ids(requests) -> set[uuid.UUID]:
    return {uuid.UUID(r.headers["webhook-id"]) for r in requests if 200 <= r.status < 300 and "webhook-id" in r.headers}


def test_kill_9_at_random_moments_loses_nothing_committed(tmp_path: Path):
    counts = Counts("kill -9")
    rng = random.Random(15)
    scenario = tmp_path / "s.toml"
    scenario.write_text("".join(scenario_node(n, 50 + i) for i, n in enumerate(NODES)))
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path)
    receiver = HttpReceiver()
    db_path = tmp_path / "gateway.db"
    config = tmp_path / "gateway.toml"
    config.write_text(gateway_config(db_path, [gateway_node(n, links, interval_s=0.1) for n in NODES])
                      + f'\n[[alerting.sinks]]\ntype = "webhook"\nname = "hook"\nurl = "{receiver.url}/hook"\n'
                      f'secret = "{SECRET}"\nmin_severity = "info"\n')
    moments: dict[str, int] = {}
    committed: dict[int, tuple] = {}
    gateway = None
    try:
        wait_for_links(links, NODES, mock)
        for round_no in range(size(1, 5)):  # during the first migration: a fresh file each time
            for path in tmp_path.glob("gateway.db*"):
                path.unlink()
            gateway = start_gateway(config, tmp_path, name=f"migrate{round_no}")
            time.sleep(rng.uniform(0.5, 4.0))  # lands before, in, or after the migration
            gateway.kill()
            gateway.close()
            counts.faults += 1
            moments["migration"] = moments.get("migration", 0) + 1
            assert _integrity(db_path) == "ok"
        for round_no in range(size(1, 36)):
            moment = MOMENTS[round_no % len(MOMENTS)]
            gateway = start_gateway(config, tmp_path, name=f"gateway{round_no}")
            stored = len(_snapshot(db_path))
            if moment == "delivery":
                seen = len(receiver.requests)
                receiver.wait_for(lambda r, seen=seen: len(r) > seen, 120, "an alert delivery")
            else:
                wait_until(lambda stored=stored: len(_snapshot(db_path)) > stored, 120, 0.05, what="a new measurement")
                if moment == "acquisition":
                    time.sleep(rng.uniform(0.0, 0.3))  # somewhere in the next cycle's node I/O
            assert "Traceback" not in gateway.stderr, gateway.stderr[-3000:]
            gateway.kill()
            gateway.close()
            counts.faults += 1
            moments[moment] = moments.get(moment, 0) + 1
            assert _integrity(db_path) == "ok"
            now = _snapshot(db_path)
            counts.lost += sum(1 for i, row in committed.items() if now.get(i) != row)
            committed = now
        # A last start delivers what is still pending: every event reaches the receiver at least once.
        gateway = start_gateway(config, tmp_path, name="final")
        wait_until(lambda: "gateway started" in gateway.stderr, 120, 0.1, what="the last start")
        events = _event_ids(db_path)
        receiver.wait_for(lambda r: events <= _delivered_ids(r), 120, "every event delivered")
        assert gateway.terminate(timeout_s=15) == 0, gateway.stderr[-3000:]
        gateway.close()
    finally:
        if gateway is not None:
            gateway.close()  # never left running: its port's pty number is soon another process's
        mock.close()
        receiver.close()
    final = _snapshot(db_path)
    counts.lost += sum(1 for i, row in committed.items() if final.get(i) != row)
    counts.checked = len(final)
    keys = [(node, boot, number) for node, boot, number, _, _ in final.values()]
    counts.duplicated = len(keys) - len(set(keys))
    counts.corrupted = sum(1 for *_, digest in final.values() if digest is None)
    counts.report(moments=moments, events_delivered=len(events))
    counts.assert_nothing_lost()
