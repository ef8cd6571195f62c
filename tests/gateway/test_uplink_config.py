"""`[uplink]`: what `--check` refuses before a start, and what the gateway's readiness says about the uplink."""
from __future__ import annotations

import subprocess
import sys
from datetime import UTC, datetime, timedelta

import pytest

from db.uplink_queue import QueueStats
from gateway.config import ConfigError, load_settings
from gateway.readiness import readiness_report
from gateway.uplink.sender import UplinkStats

NODE = '[[nodes]]\nid = "a"\nurl = "/dev/ttyUSB0"\n'
UPLINK = '[uplink]\nurl = "https://central.example.net"\ngateway_id = "gw-1"\nsite = "north"\n'
NOW = datetime(2026, 12, 1, 12, 0, tzinfo=UTC)


def _config(tmp_path, uplink: str):
    path = tmp_path / "gateway.toml"
    path.write_text(f'[database]\nurl = "sqlite:///{tmp_path / "ps.db"}"\n' + uplink + NODE)
    return path


def test_an_uplink_with_a_key_file_is_read_and_the_key_is_its_first_line(tmp_path):
    key_file = tmp_path / "uplink.key"
    key_file.write_text("psk_abc\n# a note\n")
    settings = load_settings(_config(tmp_path, UPLINK + f'key_file = "{key_file}"\n'))
    assert settings.uplink is not None and settings.uplink.read_key() == "psk_abc"
    assert settings.uplink.send == "everything"


@pytest.mark.parametrize(
    "changes, says",
    [
        ({}, "set exactly one of 'key' and 'key_file'"),
        ({"key": '"a"', "key_file": '"/etc/k"'}, "set exactly one of 'key' and 'key_file'"),
        ({"key": '"  "'}, "key is empty"),
        ({"key_file": '"{missing}"'}, r"key_file .*missing\.key: cannot read it \(No such file or directory\)"),
        ({"key_file": '"{empty}"'}, r"key_file .*empty\.key: is empty"),
        ({"key": '"k"', "url": '"ftp://central"'}, r"uplink\.url"),
        ({"key": '"k"', "gateway_id": '"gw/1"'}, r"uplink\.gateway_id"),
        ({"key": '"k"', "send": '"some"'}, r"uplink\.send"),
        ({"key": '"k"', "batch_records": "501"}, r"uplink\.batch_records"),  # the contract's limit per batch
        ({"key": '"k"', "batch_bytes": "9000000"}, r"uplink\.batch_bytes"),  # ... and per body
        ({"key": '"k"', "backoff_cap_s": "0.5"}, r"backoff_cap_s \(0\.5\) is below backoff_base_s"),
        ({"key": '"k"', "retry_after_max_s": "inf"}, r"uplink\.retry_after_max_s"),
    ],
)
def test_check_refuses_an_uplink_that_cannot_work_naming_the_key(tmp_path, changes, says):
    (tmp_path / "empty.key").write_text("\n")
    table = {"url": '"https://central.example.net"', "gateway_id": '"gw-1"', "site": '"north"', **changes}
    uplink = "[uplink]\n" + "".join(f"{key} = {value}\n" for key, value in table.items())
    uplink = uplink.format(missing=tmp_path / "missing.key", empty=tmp_path / "empty.key")
    with pytest.raises(ConfigError, match=says):
        load_settings(_config(tmp_path, uplink))


def test_the_gateway_command_says_so_in_one_line_and_exits_2(tmp_path):
    path = _config(tmp_path, UPLINK + f'key_file = "{tmp_path / "gone.key"}"\n')
    done = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(path), "--check"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "gone.key: cannot read it" in done.stderr and "Traceback" not in done.stderr


def test_readiness_fails_while_the_oldest_unsent_record_is_older_than_ready_lag_s():
    waiting = QueueStats(depth=12, oldest_pending_at=NOW - timedelta(seconds=90), refused=1)
    sender = UplinkStats(last_error="HTTP 503 busy")
    ready, body = readiness_report(dead_loops=[], now=NOW, queue=waiting, sender=sender, ready_lag_s=60)
    assert not ready and body["status"] == "not ready"
    assert body["reasons"] == ["uplink: the oldest unsent record waits 90 s, more than ready_lag_s 60 s "
                               "(last error: HTTP 503 busy)"]
    assert body["uplink"]["queue_depth"] == 12 and body["uplink"]["lag_s"] == 90.0 and body["uplink"]["refused"] == 1
    ready, body = readiness_report(dead_loops=[], now=NOW, queue=waiting, sender=sender, ready_lag_s=120)
    assert ready and body["reasons"] == []


def test_readiness_fails_when_a_loop_died_uplink_or_not():
    ready, body = readiness_report(dead_loops=["uplink"], now=NOW)
    assert not ready and body == {"status": "not ready", "reasons": ["loop uplink died (see the log)"]}
    assert readiness_report(dead_loops=[], now=NOW) == (True, {"status": "ready", "reasons": []})
