"""`--check` validates everything a start needs, opening nothing: what passes it does not die later.

Each case here passed `--check` once and then killed a thread or printed a traceback (issue 15, item 7).
"""
from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading

import pytest

from gateway import daemon
from gateway.config import ConfigError, load_settings
from gateway.worker import NodeWorker

NODE = '[[nodes]]\nid = "a"\nurl = "/dev/ttyUSB0"\n'


def _config(tmp_path, body: str, database: str | None = None):
    path = tmp_path / "gateway.toml"
    url = database if database is not None else f"sqlite:///{tmp_path / 'ps.db'}"
    path.write_text(f'[database]\nurl = "{url}"\n' + body)
    return path


@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e300"])
def test_an_interval_that_no_timer_can_wait_is_refused(tmp_path, value):
    with pytest.raises(ConfigError, match=r"nodes\.0\.interval_s"):
        load_settings(_config(tmp_path, NODE + f"interval_s = {value}\n"))


@pytest.mark.parametrize(
    "body, key",
    [
        ("reopen_backoff_max_s = inf\n" + NODE, "reopen_backoff_max_s"),
        ("shutdown_timeout_s = 1e300\n" + NODE, "shutdown_timeout_s"),
        (NODE + "timeout_s = inf\n", r"nodes\.0\.timeout_s"),
        ("[retention]\nprune_every_s = inf\n" + NODE, r"retention\.prune_every_s"),
        ('[alerting]\noffline_after_s = 1e300\n[[alerting.sinks]]\ntype = "alertmanager"\nname = "am"\n'
         'url = "http://127.0.0.1:9093"\nbackoff_cap_s = inf\n' + NODE, r"alerting\.offline_after_s.*backoff_cap_s"),
    ],
)
def test_every_duration_is_finite_and_bounded(tmp_path, body, key):
    with pytest.raises(ConfigError, match=key):
        load_settings(_config(tmp_path, body))


@pytest.mark.parametrize(
    "url, says",
    [
        ("notadb://x", "unsupported database 'notadb'"),
        ("sqlte:///ps.db", "did you mean 'sqlite'"),
        ("sqlite:///:memory:", "SQLite needs a file"),
        ("sqlite://", "SQLite needs a file"),
        ("postgresql+asyncpg://u@127.0.0.1/x", "asyncpg"),
        ("not a url", "not a database URL"),
    ],
)
def test_a_database_url_that_cannot_work_is_refused_by_name(tmp_path, url, says):
    with pytest.raises(ConfigError, match=r"database\.url: .*" + says.replace("(", r"\(")):
        load_settings(_config(tmp_path, NODE, database=url))


def test_a_sqlite_file_in_a_missing_directory_is_refused_before_anything_opens(tmp_path):
    missing = tmp_path / "no" / "such"
    with pytest.raises(ConfigError, match=f"create {missing}"):
        load_settings(_config(tmp_path, NODE, database=f"sqlite:///{missing / 'ps.db'}"))
    assert not missing.exists()


def test_a_postgresql_url_is_accepted_without_connecting(tmp_path):
    settings = load_settings(_config(tmp_path, NODE, database="postgresql+psycopg://nobody@192.0.2.1:1/none"))
    assert settings.database.url.startswith("postgresql+psycopg://")


def test_an_unknown_pyserial_scheme_is_refused(tmp_path):
    with pytest.raises(ConfigError, match=r"nodes\.0\.url: pyserial has no 'sokcet'"):
        load_settings(_config(tmp_path, '[[nodes]]\nid = "a"\nurl = "sokcet://127.0.0.1:7000"\n'))


@pytest.mark.parametrize("other", ["//dev/ttyS1", "/dev/./ttyS1", "/dev/../dev/ttyS1"])
def test_two_spellings_of_one_device_are_one_port(tmp_path, other):
    body = f'[[nodes]]\nid = "a"\nurl = "/dev/ttyS1"\n[[nodes]]\nid = "b"\nurl = "{other}"\n'
    with pytest.raises(ConfigError, match=f"two nodes share a port: /dev/ttyS1 and {other}"):
        load_settings(_config(tmp_path, body))


def test_a_stable_symlink_and_its_device_are_one_port(tmp_path):
    device = tmp_path / "ttyUSB0"
    device.touch()
    (tmp_path / "by-id").symlink_to(device)
    body = f'[[nodes]]\nid = "a"\nurl = "{tmp_path / "by-id"}"\n[[nodes]]\nid = "b"\nurl = "{device}"\n'
    with pytest.raises(ConfigError, match="share a port"):
        load_settings(_config(tmp_path, body))


def test_socket_urls_differing_only_in_case_are_one_port(tmp_path):
    body = '[[nodes]]\nid = "a"\nurl = "socket://Node-1:7000"\n[[nodes]]\nid = "b"\nurl = "SOCKET://node-1:7000"\n'
    with pytest.raises(ConfigError, match="share a port"):
        load_settings(_config(tmp_path, body))


def test_a_file_that_is_not_utf8_is_refused_with_its_line(tmp_path):
    path = tmp_path / "gateway.toml"
    path.write_bytes(b'[database]\nurl = "sqlite:///caf\xe9.db"\n' + NODE.encode())
    with pytest.raises(ConfigError, match=r"not UTF-8 text \(byte 0xe9 on line 2\)"):
        load_settings(path)


def test_a_directory_given_as_the_config_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        load_settings(tmp_path)


def test_a_malformed_nodes_variable_is_refused_by_name(tmp_path, monkeypatch):
    monkeypatch.setenv("PIPESENTRY_NODES", '[{"id": "a",')
    with pytest.raises(ConfigError, match="environment variable PIPESENTRY_NODES is not valid JSON"):
        load_settings(_config(tmp_path, NODE))


def test_the_environment_is_validated_like_the_file(tmp_path, monkeypatch):
    monkeypatch.setenv("PIPESENTRY_NODES", '[{"id": "b", "url": "socket://127.0.0.1:7001", "interval_s": 1e300}]')
    with pytest.raises(ConfigError, match=r"nodes\.0\.interval_s"):
        load_settings(_config(tmp_path, NODE))


@pytest.mark.e2e
@pytest.mark.parametrize(
    "body, says",
    [
        (NODE + "interval_s = inf\n", "nodes.0.interval_s: Input should be a finite number"),
        ('[database]\nurl = "sqlte:///x.db"\n' + NODE, "database.url: unsupported database 'sqlte'"),
    ],
)
def test_check_refuses_with_one_line_and_exit_2(tmp_path, body, says):
    path = tmp_path / "gateway.toml"
    path.write_text(body)
    proc = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(path), "--check"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and says in proc.stderr and "Traceback" not in proc.stderr


def test_a_poll_loop_that_dies_stops_the_daemon_with_exit_1_instead_of_lingering(tmp_path, monkeypatch, caplog):
    """The watchdog's stall limit is hours (or, with inf, never): a dead thread must not wait for it."""
    died = threading.Event()

    def broken_run(self: NodeWorker) -> None:
        died.set()
        raise RuntimeError("a bug outside the cycle's error handling")

    monkeypatch.setattr(NodeWorker, "run", broken_run)
    monkeypatch.setenv("WATCHDOG_USEC", "100000")  # look every 50 ms
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setattr(threading, "excepthook", threading.excepthook)  # run() installs its own; restore it after
    settings = load_settings(_config(tmp_path, '[[nodes]]\nid = "a"\nurl = "loop://"\n'))
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        with caplog.at_level(logging.ERROR, logger="pipesentry.gateway"):
            code = daemon.run(settings)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert died.is_set() and code == daemon.EXIT_LOOP_DIED
    assert "loop node-a died: RuntimeError" in caplog.text
    assert "loop node-a died (see the error above)" in caplog.text
