"""`pipesentry node-check` as a user runs it: real processes, the mock node on TCP, its documented example."""
from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import pytest

from nodecheck.requirements import REQUIREMENTS
from tests.support.process_harness import PYTHON, Proc, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(120)]
REPO = Path(__file__).resolve().parents[2]


def start_mock(tmp_path: Path, *args: str) -> tuple[Proc, str]:
    proc = Proc([PYTHON, "-m", "pipesentry", "mock-node", "--tcp", *args], tmp_path, "mock")
    line = wait_until(lambda: re.search(r"^node-01 (socket://\S+)$", proc.stdout, re.MULTILINE), 30, what="the mock's port")
    return proc, line.group(1)


def node_check(*args: str, timeout_s: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "pipesentry", "node-check", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=REPO)


def test_a_conformant_node_passes_with_one_line_per_requirement_and_exit_0(tmp_path):
    mock, url = start_mock(tmp_path)
    try:
        done = node_check(url, "--timeout-s", "0.3", "--reboot-command", f"kill -USR1 {mock.popen.pid}")
    finally:
        mock.close()
    lines = done.stdout.splitlines()
    assert done.returncode == 0, done.stdout + done.stderr
    assert [line.split()[0] for line in lines[:-1]] == [r.id for r in REQUIREMENTS]
    assert lines[-1] == f"{len(REQUIREMENTS) - 1} passed, 0 failed, 1 not applicable"
    assert re.search(r"^R-BOOT-2 +passed .*0x[0-9A-F]{8} -> 0x[0-9A-F]{8}", done.stdout, re.MULTILINE)


def test_a_violation_fails_its_line_and_exits_1(tmp_path):
    mock, url = start_mock(tmp_path, "--violation", "cached_crc_stale")
    try:
        done = node_check(url, "--timeout-s", "0.3")
    finally:
        mock.close()
    assert done.returncode == 1, done.stdout + done.stderr
    failed = [line for line in done.stdout.splitlines() if " FAILED " in line]
    assert len(failed) == 1 and failed[0].startswith("R-CACHE-2") and "[bytes: 02 83 07 00" in failed[0]
    assert re.search(r"^R-BOOT-2 +n/a .*--reboot-command", done.stdout, re.MULTILINE)


@pytest.mark.parametrize("url, says", [
    ("/dev/ttyPIPESENTRY-none", "cannot open /dev/ttyPIPESENTRY-none"),
    ("loop://", "no answer to INFO from loop://"),
    ("socket://127.0.0.1:1", "cannot open socket://127.0.0.1:1"),
])
def test_an_unreachable_node_is_one_line_on_stderr_and_exit_2(url, says):
    done = node_check(url, "--timeout-s", "0.2", "--retries", "1")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and says in done.stderr and "Traceback" not in done.stderr


def test_the_documented_example_runs_as_written(tmp_path):
    text = (REPO / "docs" / "protocol.md").read_text()
    block = re.search(r"```sh\n(pipesentry mock-node .*?)```", text, re.DOTALL).group(1)
    mock_line, check_line = [line.split("#")[0].strip() for line in block.strip().splitlines()]
    assert mock_line == "pipesentry mock-node --tcp &"
    mock, url = start_mock(tmp_path)
    try:
        port = url.rsplit(":", 1)[1]
        command = check_line.replace("PORT", port).replace("$!", str(mock.popen.pid))  # as the shell would
        args = shlex.split(command)
        assert args[:2] == ["pipesentry", "node-check"]
        done = node_check(*args[2:])
    finally:
        mock.close()
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines()[-1] == f"{len(REQUIREMENTS) - 1} passed, 0 failed, 1 not applicable"

