"""Specification of crash safety: kill -9 at random moments never leaves a half-written record."""
from __future__ import annotations

import os
import random
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select, text

from db.database import open_database
from db.measurements import load_traces
from db.models import MeasurementRow
from tests.support.db_fixtures import sample_codes

pytestmark = pytest.mark.e2e  # runs the system's real processes

ROUNDS = 5
LINE_TIMEOUT_S = 30.0
REPO_ROOT = Path(__file__).resolve().parents[2]

# The child stores measurements as fast as it can and prints each index after its commit.
WRITER = """
import sys
sys.path[:0] = [{repo!r}]
from tests.support.db_fixtures import T0, minutes, store_sample
from db.database import open_database

database = open_database(sys.argv[1])
first = int(sys.argv[2])
for index in range(first, first + 100_000):
    with database.write() as session:
        store_sample(session, acquired_at=T0 + minutes(index), seed=index)
    print(index, flush=True)
"""


def _committed_indices(process: subprocess.Popen, at_least: int) -> list[int]:
    """Indices the child reported as committed, reading until ``at_least`` arrived."""
    selector = selectors.DefaultSelector()
    selector.register(process.stdout, selectors.EVENT_READ)
    buffer = b""
    deadline = time.monotonic() + LINE_TIMEOUT_S
    while buffer.count(b"\n") < at_least:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"writer reported only {buffer.count(chr(10).encode())} commits in {LINE_TIMEOUT_S} s"
        if selector.select(timeout=remaining):
            chunk = os.read(process.stdout.fileno(), 4096)
            assert chunk, f"writer exited early: {process.wait()} {process.stderr.read().decode()[-2000:]}"
            buffer += chunk
    selector.close()
    return [int(line) for line in buffer.split(b"\n")[:-1]]


def test_kill_9_while_writing_leaves_a_consistent_database(sqlite_url):
    open_database(sqlite_url).dispose()  # schema exists before the first child starts
    seed = random.SystemRandom().randrange(2**32)
    rng = random.Random(seed)
    committed: set[int] = set()
    script = WRITER.format(repo=str(REPO_ROOT))
    for round_number in range(ROUNDS):
        process = subprocess.Popen(
            [sys.executable, "-c", script, sqlite_url, str(round_number * 100_000)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            cwd=REPO_ROOT,
        )
        try:
            committed.update(_committed_indices(process, at_least=rng.randint(1, 4)))
            time.sleep(rng.uniform(0.0, 0.05))  # land the kill anywhere inside a write
        finally:
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=10)
            leftover = process.stdout.read()
            process.stdout.close()
            process.stderr.close()
        committed.update(int(line) for line in leftover.split(b"\n") if line.strip())

    database = open_database(sqlite_url)
    try:
        with database.session() as session:
            assert session.execute(text("PRAGMA integrity_check")).scalar_one() == "ok", f"seed {seed}"
            rows = session.scalars(select(MeasurementRow)).all()
            stored = {row.node_measurement_id for row in rows}
            assert committed <= stored, f"seed {seed}: commits lost: {sorted(committed - stored)}"
            assert len(stored) == len(rows)
            for row in rows:  # every row that exists is whole and verifies
                np.testing.assert_array_equal(load_traces(row), sample_codes(row.node_measurement_id))
    finally:
        database.dispose()
