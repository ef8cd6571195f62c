"""A stop asked for while the gateway opens its database: the upgrade finishes, the daemon exits 0, no node polled."""
from __future__ import annotations

import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from db.migrate import head_revision
from tests.support.process_harness import gateway_config

# The real daemon in a real process; SIGTERM is sent to it from inside the schema upgrade, as systemd's
# stop would arrive while a large database is being migrated on the first start of a new version.
CHILD = textwrap.dedent("""
    import logging, os, signal, sys
    import db.migrate
    from gateway.config import load_settings
    from gateway.daemon import run

    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(message)s")
    real_upgrade = db.migrate.command.upgrade

    def upgrade_interrupted(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return real_upgrade(*args, **kwargs)

    db.migrate.command.upgrade = upgrade_interrupted
    sys.exit(run(load_settings(sys.argv[1])))
""")


@pytest.mark.e2e
def test_sigterm_during_the_schema_upgrade_lets_it_finish_and_exits_0_before_polling(tmp_path: Path):
    path = tmp_path / "pipesentry.db"
    config = tmp_path / "gateway.toml"
    config.write_text(gateway_config(path, [{"id": "n1", "url": "socket://127.0.0.1:9", "interval_s": 0.5}]))
    done = subprocess.run([sys.executable, "-c", CHILD, str(config)], capture_output=True, text=True, timeout=60)
    killed = f" (killed by {signal.Signals(-done.returncode).name})" if done.returncode < 0 else ""
    assert done.returncode == 0, f"exit {done.returncode}{killed}: {done.stderr}"
    assert "received SIGTERM, shutting down" in done.stderr
    assert "gateway stopped before polling any node" in done.stderr
    assert "gateway started" not in done.stderr  # no worker, no metrics port, no uplink: nothing ran
    assert "Traceback" not in done.stderr
    with sqlite3.connect(path) as conn:  # the upgrade ran to its end: the next start has nothing to redo
        assert conn.execute("SELECT version_num FROM alembic_version").fetchone() == (head_revision(),)
