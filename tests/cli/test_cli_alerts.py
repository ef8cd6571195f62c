"""`pipesentry alerts deliver` and its alias `python -m alerts deliver` as an operator runs them."""
from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.e2e  # runs the installed commands as processes

COMMANDS = {"pipesentry": ["-m", "pipesentry", "alerts", "deliver"], "alias": ["-m", "alerts", "deliver"]}


def run(command: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *COMMANDS[command], *args], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_bad_config_is_one_line_and_exit_2(tmp_path, command):
    config = tmp_path / "gateway.toml"
    config.write_text('[[nodes]]\nid = "a"\nurl = "/dev/x"\ninterval_s = 0\n')
    result = run(command, "--config", str(config))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and "nodes.0.interval_s" in result.stderr


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_database_without_the_schema_is_one_line_and_exit_2(tmp_path, command):
    config = tmp_path / "gateway.toml"
    config.write_text(f'[database]\nurl = "sqlite:///{tmp_path / "empty.db"}"\n[[nodes]]\nid = "a"\nurl = "loop://"\n')
    result = run(command, "--config", str(config))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and "schema" in result.stderr
