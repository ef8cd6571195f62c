"""The gateway started on a database it must not use: one clear line, exit 2, the file untouched."""
from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.config import load_settings
from gateway.daemon import run
from tests.support.bad_databases import BAD_FILES
from tests.support.process_harness import gateway_config

REASONS = {
    "garbage": "is damaged, not opened",
    "truncated": "is damaged, not opened",
    "other-format": "is damaged, not opened",
    "foreign-sqlite": "is not PipeSentry's",
    "corrupt-pages": "quick_check found corrupt pages",
}


def _config(tmp_path: Path, kind: str) -> tuple[Path, Path]:
    path = tmp_path / "pipesentry.db"
    BAD_FILES[kind](path)
    config = tmp_path / "gateway.toml"
    # A node that never answers: the gateway must stop before it polls anything.
    config.write_text(gateway_config(path, [{"id": "n1", "url": "socket://127.0.0.1:9", "interval_s": 60.0}]))
    return path, config


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_the_gateway_refuses_a_bad_database_file_with_one_error_line_and_exit_2(kind: str, tmp_path: Path, caplog):
    path, config = _config(tmp_path, kind)
    before = path.read_bytes()
    with caplog.at_level(logging.INFO, logger="pipesentry"):
        assert run(load_settings(config)) == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and REASONS[kind] in errors[0].getMessage()
    assert errors[0].exc_info is None and "\n" not in errors[0].getMessage()
    assert path.read_bytes() == before


@pytest.mark.e2e  # the installed command, a real process
def test_the_gateway_command_on_a_garbage_file_prints_no_traceback(tmp_path: Path):
    _, config = _config(tmp_path, "garbage")
    done = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(config)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "is damaged, not opened" in done.stderr
