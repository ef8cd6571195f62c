"""`pipesentry apikey create|list|revoke` and `pipesentry api` as an operator runs them."""
from __future__ import annotations

import signal
import sys
from pathlib import Path

import httpx
import pytest
import typer
from typer.testing import CliRunner

from pipesentry.commands.api import api
from pipesentry.commands.apikey import apikey_app
from service.settings import ApiSettings
from tests.support.api_fixtures import DAMAGED_NODE, copy_database, fleet_database, free_port
from tests.support.process_harness import Proc, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(180)]  # runs the system's real processes


@pytest.fixture(scope="module")
def db_url(tmp_path_factory) -> str:
    path = copy_database(fleet_database(tmp_path_factory.getbasetemp()), tmp_path_factory.mktemp("cli") / "cli.db")
    return f"sqlite:///{path}"


def apikey(*args: str):
    return CliRunner().invoke(apikey_app, list(args))


def test_created_key_is_printed_once_and_works_until_revoked(db_url, tmp_path):
    created = apikey("create", "--name", "field-laptop", "--role", "operator", "--database-url", db_url)
    assert created.exit_code == 0, created.output
    token = created.stdout.strip().splitlines()[-1]
    assert token.startswith("psk_")
    listing = apikey("list", "--database-url", db_url)
    assert listing.exit_code == 0 and "field-laptop\t" in listing.stdout and "operator" in listing.stdout
    assert token not in listing.stdout  # only the display prefix is ever shown again
    key_id = next(line.split("\t")[0] for line in listing.stdout.splitlines() if "field-laptop" in line)

    port = free_port()
    server = Proc([sys.executable, "-c", "import typer; from pipesentry.commands.api import api; typer.run(api)",
                   "--database-url", db_url, "--port", str(port), "--log-level", "warning"], tmp_path, "api")
    try:
        base = f"http://127.0.0.1:{port}"

        def ready() -> bool:
            assert server.alive(), server.stderr[-2000:]
            return httpx.get(f"{base}/readyz", timeout=2).status_code == 200

        wait_until(ready, 30, 0.1, what="pipesentry api ready")
        headers = {"Authorization": f"Bearer {token}"}
        node = httpx.get(f"{base}/api/v1/nodes/{DAMAGED_NODE}", headers=headers, timeout=10)
        assert node.status_code == 200 and node.json()["state"] == "damage"
        revoked = apikey("revoke", key_id, "--database-url", db_url)
        assert revoked.exit_code == 0 and "revoked" in revoked.stdout
        # Revoked from outside the API process: refused within the key cache's TTL (10 s by default).
        wait_until(lambda: httpx.get(f"{base}/api/v1/nodes", headers=headers, timeout=10).status_code == 401,
                   ApiSettings().key_cache_ttl_s + 5, 0.5, what="the revoked key to be refused")
        # uvicorn shuts down gracefully, then re-raises SIGTERM so the exit status tells why.
        assert server.terminate() in (0, -signal.SIGTERM), server.stderr[-2000:]
    finally:
        server.close()


def test_bad_role_unknown_key_and_missing_database_are_one_line_errors(db_url, tmp_path: Path):
    bad_role = apikey("create", "--name", "x", "--role", "root", "--database-url", db_url)
    assert bad_role.exit_code == 2 and "--role must be one of viewer, operator, admin" in bad_role.output
    unknown = apikey("revoke", "999999", "--database-url", db_url)
    assert unknown.exit_code == 2 and "no API key 999999" in unknown.output
    missing = tmp_path / "nowhere.db"
    absent = apikey("list", "--database-url", f"sqlite:///{missing}")
    assert absent.exit_code == 2 and "no database file" in absent.output and "Traceback" not in absent.output
    assert not missing.exists()


def test_api_command_refuses_bad_settings_in_one_line():
    app = typer.Typer()
    app.command()(api)
    result = CliRunner().invoke(app, ["--port", "70000"])
    assert result.exit_code == 2 and result.output.startswith("error: port:")
