"""Central mode: docker/compose.yaml's API command, run from the installed wheel with 2 workers on
PostgreSQL, with keys made by the CLI.

The processes share nothing but the database: a key revoked from outside them (the CLI) stops on
every worker within the key cache's stated TTL, and a gateway key made with `--role gateway --site`
ingests through any worker.
"""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

from db.api_keys import create_api_key
from db.database import open_database
from db.models import Role
from tests.support.api_fixtures import free_port
from tests.support.ingest_batches import batch_of, node_history
from tests.support.process_harness import Proc, wait_until
from tests.support.wheel_fixtures import REPO
from uplink.contract import INGEST_PATH

pytestmark = [pytest.mark.e2e, pytest.mark.postgres, pytest.mark.timeout(120)]

BIN = Path(sys.executable).parent
COMPOSE = REPO / "docker" / "compose.yaml"
TTL_S = 2.0
REQUESTS = 20  # each on a new connection, so the kernel hands them to both workers


def cli(*args: str, url: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN / "pipesentry"), *args, "--database-url", url], capture_output=True, text=True,
                          timeout=60)


def token_of(created: subprocess.CompletedProcess[str]) -> str:
    assert created.returncode == 0, created.stderr
    return created.stdout.strip().splitlines()[-1]


def worker_pids(parent: int) -> list[int]:
    """uvicorn's worker processes (multiprocessing's spawned children; not its resource tracker)."""
    children = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    return [int(pid) for pid in children if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()]


def statuses(url: str, token: str) -> list[int]:
    return [httpx.get(url, headers={"Authorization": f"Bearer {token}", "Connection": "close"}, timeout=10).status_code
            for _ in range(REQUESTS)]


def compose_api_command(workers: int) -> list[str]:
    """The compose file's API command (after the image's entry point), with ``workers`` workers."""
    command = list(yaml.safe_load(COMPOSE.read_text())["services"]["api"]["command"])
    command[command.index("--workers") + 1] = str(workers)
    return ["pipesentry", *command]


def test_two_workers_on_postgresql_share_keys_and_a_revoked_key_stops_within_the_ttl(
    postgres_url: str, tmp_path, installed_wheel: Path
):
    database = open_database(postgres_url)  # the central site's schema, as `python -m db upgrade` makes it
    with database.write() as session:
        viewer_row, viewer = create_api_key(session, name="ops-screen", role=Role.VIEWER)
        viewer_id = viewer_row.id
    database.dispose()
    gateway = token_of(cli("apikey", "create", "--name", "gw-north-1", "--role", "gateway", "--site", "north",
                           url=postgres_url))

    port = free_port()
    program, *arguments = compose_api_command(workers=2)
    server = Proc([str(installed_wheel / "bin" / program), *arguments, "--port", str(port), "--log-level", "warning"],
                  tmp_path, "api", env={"PIPESENTRY_API_KEY_CACHE_TTL_S": str(TTL_S),
                                        "PIPESENTRY_API_DATABASE_URL": postgres_url})
    base = f"http://127.0.0.1:{port}"
    try:
        def ready() -> bool:
            assert server.alive(), server.stderr[-2000:]
            try:
                return httpx.get(f"{base}/readyz", timeout=2).status_code == 200 and len(worker_pids(server.popen.pid)) == 2
            except httpx.TransportError:
                return False

        wait_until(ready, 60, 0.2, what="two API workers ready")
        assert set(statuses(f"{base}/api/v1/nodes", viewer)) == {200}  # cached by whichever worker served it
        stored = httpx.post(f"{base}{INGEST_PATH}", timeout=30, headers={"Authorization": f"Bearer {gateway}"},
                            content=batch_of("gw-n1", "north", node_history("gw-n1", "pipe-1", 1, 2))
                            .model_dump_json())
        assert stored.status_code == 200 and stored.json()["accepted"] == 5, stored.text
        listed = httpx.get(f"{base}/api/v1/nodes", headers={"Authorization": f"Bearer {viewer}"}, timeout=10).json()
        assert [n["node_id"] for n in listed] == ["pipe-1"]

        assert cli("apikey", "revoke", str(viewer_id), url=postgres_url).returncode == 0  # outside both workers
        time.sleep(TTL_S + 1.0)  # the stated bound: the cache's TTL, and a margin
        assert set(statuses(f"{base}/api/v1/nodes", viewer)) == {401}  # on every worker
    finally:
        server.terminate()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(server.popen.pid, signal.SIGKILL)  # the workers, if the parent left any
        server.close()

