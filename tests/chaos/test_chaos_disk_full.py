"""Chaos: the database's file system fills up under the running gateway (a real process on a tmpfs
the test mounts) and is freed again. What must hold: the gateway keeps running, its metrics say
storage unavailable, the API's /readyz answers 503 storage_unavailable; once space is freed, writes
resume without a restart, a storage_unavailable event tells the outage, and nothing committed is
lost, duplicated or corrupted."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import httpx
import pytest

from db.models import EventRow
from service.settings import ApiSettings
from tests.support.api_fixtures import ApiServer
from tests.support.chaos import Counts, size
from tests.support.process_harness import (
    gateway_config,
    gateway_metrics_port,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)
from tests.support.small_filesystem import MIB, fill, shrink, small_filesystem

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(300)]  # a mock node and the gateway as real processes

NODE = "full-a"


def _rows(db_path: Path) -> list[tuple[int, int | None, int, bytes | None]]:
    with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True) as connection:
        return connection.execute(
            "SELECT id, boot_id, node_measurement_id, traces_blob FROM measurements ORDER BY id").fetchall()


def _metric(port: int, name: str) -> float | None:
    for line in httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return None


def test_a_full_disk_is_reported_everywhere_and_writes_resume_once_space_is_freed(tmp_path: Path):
    counts = Counts("disk full")
    scenario = tmp_path / "s.toml"
    scenario.write_text(scenario_node(NODE, 41))
    links = tmp_path / "links"
    mock = start_mock_nodes(scenario, links, tmp_path)
    gateway = None
    with small_filesystem(tmp_path / "fs", size_mib=48) as fs:
        try:
            wait_for_links(links, [NODE], mock)
            db_path = fs / "gateway.db"
            config = tmp_path / "gateway.toml"
            config.write_text(gateway_config(db_path, [gateway_node(NODE, links, interval_s=0.2)]))
            gateway = start_gateway(config, tmp_path)
            port = gateway_metrics_port(gateway)
            wait_until(lambda: len(_rows(db_path)) >= 3, 120, 0.2, what="three measurements")
            api = ApiServer(ApiSettings(database_url=f"sqlite:///{db_path}"))
            with api:
                assert httpx.get(f"{api.base_url}/readyz").status_code == 200
                for outage in range(size(1, 3)):
                    filler = fill(fs, leave_bytes=64 * 1024, name=f"filler-{outage}")
                    counts.faults += 1
                    wait_until(lambda: _metric(port, "pipesentry_gateway_storage_available") == 0.0, 120, 0.2,
                               what="the gateway's metrics to say storage unavailable")
                    before = _rows(db_path)
                    ready = httpx.get(f"{api.base_url}/readyz")
                    assert ready.status_code == 503 and ready.json()["reason"] == "storage_unavailable", ready.text
                    assert gateway.alive()
                    shrink(filler, 16 * MIB)  # space freed: more than min_free_bytes, no restart
                    wait_until(lambda: _metric(port, "pipesentry_gateway_storage_available") == 1.0, 120, 0.2,
                               what="writes to resume")
                    grown = len(before) + 2
                    wait_until(lambda n=grown: len(_rows(db_path)) >= n, 120, 0.2, what="new measurements")
                    assert httpx.get(f"{api.base_url}/readyz").status_code == 200
                    kept = {r[0]: r for r in _rows(db_path)}
                    counts.lost += sum(1 for r in before if kept.get(r[0]) != r)  # committed then lost or changed
                    filler.unlink()
            wait_until(lambda: _events(db_path) >= size(1, 3), 60, 0.2, what="a storage_unavailable event per outage")
        finally:
            if gateway is not None:
                assert gateway.terminate(timeout_s=15) == 0, gateway.stderr[-3000:]
                gateway.close()
            mock.close()
        rows = _rows(db_path)
        with sqlite3.connect(db_path) as connection:
            assert connection.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        counts.checked = len(rows)
        keys = [(boot, number) for _, boot, number, _ in rows]
        counts.duplicated = len(keys) - len(set(keys))
        counts.corrupted = sum(1 for r in rows if r[3] is None)  # a row without its traces: half-written
    assert "Traceback" not in gateway.stderr
    counts.report(storage_unavailable_events=size(1, 3))
    counts.assert_nothing_lost()


def _events(db_path: Path) -> int:
    with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True) as connection:
        return connection.execute(f"SELECT count(*) FROM {EventRow.__tablename__} WHERE kind = "
                                  "'storage_unavailable'").fetchone()[0]
