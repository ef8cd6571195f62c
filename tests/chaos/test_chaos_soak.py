"""Chaos soak: 16 nodes at the highest cadence the config takes, polled by the gateway (its threads in
this process) for a bounded number of cycles, printing memory and open files at the start and the end.
What must hold: every node stored its measurements, none lost or duplicated, and the open files at the
end are those at the start (no leak per cycle). The full soak runs under ``make chaos``."""
from __future__ import annotations

import os
import resource
from pathlib import Path

import pytest
from sqlalchemy import select, text

from db.database import open_database
from db.models import MeasurementRow
from gateway.config import load_settings
from gateway.daemon import Gateway
from mocknode.scenario import default_scenario
from mocknode.server import MockNodeServer
from tests.support.chaos import FULL, Counts, size
from tests.support.process_harness import gateway_config, gateway_node, wait_until

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.timeout(3600),
    pytest.mark.skipif(not FULL, reason="the soak runs under make chaos (PIPESENTRY_CHAOS_FULL=1)"),
]

N_NODES = 16
FASTEST_S = 0.05  # far below what a cycle takes: every node polls back to back


def _rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _open_files() -> int:
    return len(os.listdir("/proc/self/fd"))


def _counts(database) -> dict[str, int]:
    with database.session() as session:
        ids = list(session.execute(select(MeasurementRow.node_id)).scalars())
    return {n: ids.count(n) for n in set(ids)}


def test_sixteen_nodes_at_the_highest_cadence_leak_nothing(tmp_path: Path):
    counts = Counts("soak")
    template = default_scenario(1).nodes[0]
    names = [f"soak-{i:02d}" for i in range(N_NODES)]
    scenarios = [template.model_copy(update={"node_id": n, "seed": 80 + i}) for i, n in enumerate(names)]
    per_node = size(3, 40)
    links = tmp_path / "links"
    with MockNodeServer(scenarios, link_dir=links):
        config = tmp_path / "gateway.toml"
        config.write_text(gateway_config(tmp_path / "g.db", [gateway_node(n, links, interval_s=FASTEST_S) for n in names]))
        settings = load_settings(config)
        database = open_database(settings.database.url)
        gateway = Gateway(settings, database)
        gateway.start()
        try:
            wait_until(lambda: len(c := _counts(database)) == N_NODES and min(c.values()) >= 2, 600, 0.5,
                       what="every node polling")
            start = (_rss_mib(), _open_files())
            wait_until(lambda: min(_counts(database).values()) >= per_node + 2, 3000, 0.5,
                       what=f"{per_node} more measurements per node")
            end = (_rss_mib(), _open_files())
        finally:
            gateway.shutdown(settings.shutdown_timeout_s)
    with database.session() as session:
        assert session.execute(text("PRAGMA integrity_check")).scalar_one() == "ok"
        rows = session.execute(select(MeasurementRow.node_id, MeasurementRow.boot_id,
                                      MeasurementRow.node_measurement_id)).all()
    database.dispose()
    counts.checked = len(rows)
    counts.duplicated = len(rows) - len(set(rows))
    print(f"soak: {N_NODES} nodes, memory {start[0]:.0f} MiB -> {end[0]:.0f} MiB, "
          f"open files {start[1]} -> {end[1]}")
    counts.report(nodes=N_NODES)
    counts.assert_nothing_lost()
    assert end[1] <= start[1] + 2, f"open files grew from {start[1]} to {end[1]}"
