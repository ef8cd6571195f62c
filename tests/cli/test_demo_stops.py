"""`pipesentry demo` leaves nothing behind however it is stopped, and its summary only claims what happened.

`kill -TERM` of the demo, or its terminal closing (SIGHUP), used to leave the mock nodes, the
gateway and the API running as orphans, still writing (issue 16, item 3).
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from pipesentry.demo_progress import Progress
from tests.support.process_harness import wait_until

STARTUP_S = 120.0  # mock nodes, the gateway's schema, a key, the API: ~10 s alone, more on a busy machine


def _processes_mentioning(marker: str) -> list[int]:
    """Pids whose command line names ``marker`` (the demo's own out dir: nothing else on the machine does)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue  # ended meanwhile, or not ours to read
        if marker.encode() in cmdline:
            pids.append(int(entry.name))
    return pids


@pytest.mark.e2e
@pytest.mark.timeout(300)
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_signal_stops_every_child_of_the_demo(tmp_path, stop_signal):
    out_dir = tmp_path / "demo-out"
    log = (tmp_path / "demo.log").open("wb")
    taken = socket.socket()  # someone else's server on the port asked for: the demo says it moves
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    demo = subprocess.Popen(
        [sys.executable, "-m", "pipesentry", "demo", "--duration-s", "600", "--out-dir", str(out_dir),
         "--port", str(port)],
        stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
    )
    try:
        wait_until(lambda: demo.poll() is not None or b"dashboard: http://" in (tmp_path / "demo.log").read_bytes(),
                   STARTUP_S, 0.2, what="the demo's dashboard line")
        assert demo.poll() is None, (tmp_path / "demo.log").read_text()
        children = [pid for pid in _processes_mentioning(str(out_dir)) if pid != demo.pid]
        assert len(children) >= 3, children  # mock nodes, gateway, API
        demo.send_signal(stop_signal)
        assert demo.wait(60) == 0
        wait_until(lambda: not _processes_mentioning(str(out_dir)), 20, 0.2, what="no process of the demo left")
        output = (tmp_path / "demo.log").read_text()
        assert f"stopping on {signal.Signals(stop_signal).name}" in output and "stopped cleanly" in output
        assert f"port {port} is taken on 127.0.0.1: the API and dashboard use port" in output
        assert f"dashboard: http://127.0.0.1:{port}/" not in output
    finally:
        taken.close()
        if demo.poll() is None:
            demo.kill()
            demo.wait(10)
        for pid in _processes_mentioning(str(out_dir)):  # only if the test failed: do not leave them either
            os.kill(pid, signal.SIGKILL)
        log.close()


class _Detection:
    def __init__(self, axial_mm: float, angle_deg: float, defects: list) -> None:
        self.axial_mm, self.angle_deg, self.defects = axial_mm, angle_deg, defects


NOTCH = [(200.0, 90.0, 45.0)]  # axial_mm, angle_deg, appears_at_s


def test_the_summary_reports_no_error_for_a_defect_that_does_not_exist_yet():
    progress = Progress("sqlite:///unused.db", {"node-01": NOTCH})
    line = progress.verdict("node-01", _Detection(287.0, 10.0, []), elapsed_s=30.0)
    assert line == "  node-01: its defect appears 45 s in; the demo stopped at 30 s"


def test_the_summary_says_a_present_defect_was_not_flagged_rather_than_measuring_a_noise_peak():
    progress = Progress("sqlite:///unused.db", {"node-01": NOTCH})
    line = progress.verdict("node-01", _Detection(287.0, 10.0, []), elapsed_s=60.0)
    assert line is not None and "not flagged" in line and "error" not in line


def test_the_summary_measures_the_error_of_a_flagged_defect():
    progress = Progress("sqlite:///unused.db", {"node-01": NOTCH})
    line = progress.verdict("node-01", _Detection(202.0, 90.0, [{"axial_mm": 202.0}]), elapsed_s=60.0)
    assert line is not None and line.endswith("truth 200 mm, 90 deg, error 2.0 mm")


def test_a_node_without_a_simulated_defect_has_no_verdict_line():
    assert Progress("sqlite:///unused.db", {"node-02": []}).verdict("node-02", None, 60.0) is None


def test_a_signal_that_lands_in_a_finaliser_still_stops_the_demo():
    """The handler used to raise: landing in a garbage collector's callback, the exception was printed
    and dropped, and the demo ran on, deaf to every later signal (seen with SIGHUP)."""
    import gc
    import time

    from pipesentry.commands.demo import Stopped, StopSignals

    class SignalsInItsFinaliser:
        def __del__(self) -> None:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(0.05)  # the handler runs here, inside the finaliser

    before = signal.getsignal(signal.SIGHUP)
    with StopSignals() as signals:
        SignalsInItsFinaliser()
        gc.collect()
        started = time.monotonic()
        with pytest.raises(Stopped, match="SIGHUP"):
            signals.sleep(10.0)
        assert time.monotonic() - started < 1.0
    assert signal.getsignal(signal.SIGHUP) == before  # the previous handler is back
