"""A mistyped database URL is refused by every command with one line and exit 2, before anything opens.

It used to pass `--check`, then the gateway, `apikey` and `python -m db` died with a 55-line
traceback and the API answered 500 to every request (issue 16, item 2).
"""
from __future__ import annotations

import subprocess
import sys

import pytest
from pydantic import ValidationError

from service.settings import ApiSettings

TYPO = "sqlte:///{dir}/ps.db"
SAYS = "unsupported database 'sqlte'"


def _commands(tmp_path, url: str) -> dict[str, list[str]]:
    config = tmp_path / "gateway.toml"
    config.write_text(f'[database]\nurl = "{url}"\n[[nodes]]\nid = "a"\nurl = "loop://"\n')
    ps = [sys.executable, "-m", "pipesentry"]
    return {
        "gateway --check": [*ps, "gateway", "--config", str(config), "--check"],
        "gateway": [*ps, "gateway", "--config", str(config)],
        "apikey create": [*ps, "apikey", "create", "--name", "x", "--database-url", url],
        "apikey list": [*ps, "apikey", "list", "--database-url", url],
        "api": [*ps, "api", "--database-url", url],  # refused before it binds a port
        "python -m db upgrade": [sys.executable, "-m", "db", "upgrade", "--url", url],
        "python -m db current": [sys.executable, "-m", "db", "current", "--url", url],
    }


@pytest.mark.e2e
@pytest.mark.parametrize(
    "command",
    ["gateway --check", "gateway", "apikey create", "apikey list", "api", "python -m db upgrade", "python -m db current"],
)
def test_every_command_refuses_a_mistyped_url_in_one_line(tmp_path, command):
    url = TYPO.format(dir=tmp_path)
    proc = subprocess.run(_commands(tmp_path, url)[command], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and SAYS in proc.stderr, proc.stderr
    assert "did you mean 'sqlite'" in proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gateway.toml"]  # nothing created


@pytest.mark.e2e
def test_db_current_does_not_create_a_missing_sqlite_file(tmp_path):
    missing = tmp_path / "absent.db"
    proc = subprocess.run([sys.executable, "-m", "db", "current", "--url", f"sqlite:///{missing}"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "no database file" in proc.stderr and not missing.exists()


@pytest.mark.parametrize("url", ["sqlte:///x.db", "notadb://x", "sqlite:///:memory:", "sqlite:////no/such/dir/x.db"])
def test_the_api_refuses_to_start_on_a_url_that_cannot_work(url):
    with pytest.raises(ValidationError, match="database_url"):
        ApiSettings(database_url=url)


def test_the_api_still_starts_before_the_gateway_created_the_file(tmp_path):
    """A missing file in an existing directory is normal at first boot: /readyz says so (503) until it exists."""
    assert ApiSettings(database_url=f"sqlite:///{tmp_path / 'later.db'}").database_url.endswith("later.db")


def _closed_port() -> int:
    import socket

    with socket.socket() as probe:  # bound and closed again: nothing listens there
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.e2e
@pytest.mark.parametrize(
    "command", ["gateway", "alerts deliver", "apikey list", "python -m db upgrade", "python -m db current"],
)
def test_every_command_says_so_when_the_postgresql_server_cannot_be_reached(tmp_path, command):
    """A PostgreSQL server that is down (or a host name that does not resolve: the same
    driver error, with no SQLSTATE) used to end these commands in a traceback with exit 1."""
    url = f"postgresql+psycopg://pipesentry@127.0.0.1:{_closed_port()}/test"
    commands = _commands(tmp_path, url)
    commands["alerts deliver"] = [sys.executable, "-m", "pipesentry", "alerts", "deliver",
                                  "--config", str(tmp_path / "gateway.toml")]
    proc = subprocess.run(commands[command], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert "cannot reach the database server" in proc.stderr and "Connection refused" in proc.stderr, proc.stderr
