"""The gateway's NodeClient against the mock node on a real pseudo-terminal and on TCP 127.0.0.1."""
from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from gateway.node_client import NodeClient
from gateway.node_errors import NodeError, NodeTimeout
from imaging.grid import Grid
from mocknode.faults import FaultSpec
from mocknode.scenario import NodeScenario, default_scenario
from mocknode.server import MockNodeServer
from nodelink.transport import PortVanished, SerialTransport
from protocol.framing import FLAG_CACHED, Frame, FrameDecoder, encode_frame
from protocol.messages import AcquireReply, AcquireRequest, ErrorCode, decode_message

pytestmark = pytest.mark.timeout(30)
REPO = Path(__file__).resolve().parents[2]


def make_scenario(n_samples: int = 6000, **faults) -> NodeScenario:
    base = default_scenario(1).nodes[0]
    acquisition = base.acquisition.model_copy(update={"n_samples": n_samples})
    return base.model_copy(update={"acquisition": acquisition, "faults": FaultSpec(**faults)})


@pytest.fixture(params=["pty", "tcp"])
def served(request):
    with MockNodeServer([make_scenario()], kind=request.param) as server:
        runner = server.runners["node-01"]
        yield runner
    assert not runner.is_alive()


@pytest.fixture
def client(served):
    with NodeClient(served.url, timeout_s=1.0, retries=2, backoff_s=0.01) as c:
        yield c


def test_info_reports_identity_capabilities_and_geometry(client):
    info = client.info()
    assert info.node_id == "node-01"
    assert info.protocol_version == 2 and (info.version_min, info.version_max) == (1, 2)
    assert info.n_channels == info.n_rx == 16 and info.adc_bits == 10
    assert info.fs_hz == 10e6 and info.decimation == 10
    assert info.tx_rx_distance_mm == 400.0
    assert info.circumference_mm == pytest.approx(np.pi * 114.6, rel=1e-6)
    assert info.rx_angles_deg[:3] == pytest.approx((0.0, 22.5, 45.0))
    assert info.chunk_bytes == 2048 and info.max_frame_bytes == 4096


def test_status_shows_the_baseline_only_after_a_baseline_acquisition(client):
    assert not client.status().baseline_stored
    reply = client.acquire(baseline=True)
    status = client.status()
    assert status.baseline_stored and status.baseline_id == reply.measurement_id
    assert status.n_measurements == 1 and status.supply_v == pytest.approx(5.0)


def test_read_traces_returns_exactly_the_stored_codes(client, served):
    acquired = client.acquire(baseline=False)
    transfer = client.read_traces(acquired.measurement_id)
    oracle = served.node.stored_codes(acquired.measurement_id)
    assert transfer.codes.dtype == np.int16 and transfer.codes.shape == (16, 6000)
    np.testing.assert_array_equal(transfer.codes, oracle)
    assert transfer.volts_per_code == pytest.approx(0.25 / 512)
    assert transfer.temperature_c == pytest.approx(acquired.temperature_c)
    assert transfer.chunks_rerequested == 0


def test_read_traces_selects_channels_and_a_sample_range(client, served):
    acquired = client.acquire(baseline=False)
    transfer = client.read_traces(acquired.measurement_id, channels=[1, 5], start=1000, count=333)
    oracle = served.node.stored_codes(acquired.measurement_id)
    assert transfer.channels == (1, 5)
    np.testing.assert_array_equal(transfer.codes, oracle[[1, 5], 1000:1333])


def test_configure_is_applied_to_the_next_acquisition(client, served):
    applied = client.configure(excitation_hz=75e3, cycles=5, averaging=4, n_samples=2500, channels=[0, 2, 4, 6])
    assert (applied.excitation_hz, applied.averaging, applied.n_samples) == (75e3, 4, 2500)
    acquired = client.acquire(baseline=True)
    transfer = client.read_traces(acquired.measurement_id, channels=[0, 2, 4, 6])
    assert transfer.codes.shape == (4, 2500)


def test_configure_out_of_range_is_a_node_error_with_code(client):
    with pytest.raises(NodeError) as caught:
        client.configure(excitation_hz=75e3, cycles=5, averaging=4, n_samples=10**6)
    assert caught.value.code == ErrorCode.BAD_ARGUMENT


def test_on_board_di_map_is_read_back_verified(client):
    client.acquire(baseline=True)
    current = client.acquire(baseline=False)
    computed = client.compute_di(current.measurement_id)
    di = client.read_di(computed.di_id)
    assert di.pixels.shape == (computed.n_axial, computed.n_angle) == (201, 180)
    assert di.decimation == 10 and di.grid.axial_step_mm == 2.0
    assert np.all(np.isfinite(di.pixels))
    assert float(di.pixels.max()) == pytest.approx(computed.peak_value)


def test_di_on_a_requested_grid(client):
    client.acquire(baseline=True)
    current = client.acquire(baseline=False)
    grid = Grid(100.0, 5.0, 41, 0.0, 10.0, 36)
    di = client.read_di(client.compute_di(current.measurement_id, grid=grid, decimation=5).di_id)
    assert di.grid == grid and di.pixels.shape == (41, 36)


def test_unknown_measurement_and_missing_baseline_are_typed_node_errors(client):
    with pytest.raises(NodeError) as no_measurement:
        client.read_traces(77)
    assert no_measurement.value.code == ErrorCode.NO_SUCH_MEASUREMENT
    current = client.acquire(baseline=False)
    with pytest.raises(NodeError) as no_baseline:
        client.compute_di(current.measurement_id)
    assert no_baseline.value.code == ErrorCode.NO_BASELINE


def test_ram_keeps_a_few_measurements_and_never_evicts_the_baseline(client):
    baseline = client.acquire(baseline=True)
    ids = [client.acquire(baseline=False).measurement_id for _ in range(5)]
    assert client.status().n_measurements == 4
    with pytest.raises(NodeError):
        client.read_traces(ids[0], count=10)
    assert client.read_traces(baseline.measurement_id, count=10).is_baseline
    assert client.read_traces(ids[-1], count=10).measurement_id == ids[-1]


def test_a_repeated_acquire_request_id_returns_the_cached_reply_without_acquiring_again(served):
    transport = SerialTransport(served.url)
    decoder = FrameDecoder()
    request = encode_frame(Frame(AcquireRequest.TYPE, 4242, AcquireRequest(0).encode(), seq=1))
    replies = []
    try:
        for attempt in range(2):
            transport.write(request)
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and len(replies) < attempt + 1:
                replies += decoder.feed(transport.read(0.1))
    finally:
        transport.close()
    first, second = replies
    assert decode_message(first.msg_type, first.payload) == decode_message(second.msg_type, second.payload)
    assert isinstance(decode_message(first.msg_type, first.payload), AcquireReply)
    assert not first.flags & FLAG_CACHED and second.flags & FLAG_CACHED
    assert served.node.stored_codes(1) is not None and served.node.stored_codes(2) is None


def test_loop_url_with_no_node_behind_it_times_out():
    with NodeClient("loop://", timeout_s=0.1, retries=1, backoff_s=0.01) as c:
        started = time.monotonic()
        with pytest.raises(NodeTimeout):
            c.status()
        assert time.monotonic() - started < 2.0


def test_opening_a_missing_device_is_port_vanished(tmp_path):
    with pytest.raises(PortVanished):
        NodeClient(str(tmp_path / "ttyUSB9"))


def _hung_up_pty_transport() -> SerialTransport:
    master, slave = os.openpty()
    transport = SerialTransport(os.ttyname(slave))
    os.close(slave)
    os.close(master)
    return transport


def test_a_pty_whose_other_end_closed_is_port_vanished_on_write_and_on_flush():
    """An unplugged USB-UART: write() fails with EIO, and termios calls (the flush after a write,
    discarding input) fail with termios.error, which is not an OSError: both are PortVanished."""
    transport = _hung_up_pty_transport()
    with pytest.raises(PortVanished):
        transport.discard_input()  # tcflush on the hung-up pty: termios.error
    assert not transport.is_open
    transport = _hung_up_pty_transport()
    with pytest.raises(PortVanished):
        for _ in range(50):  # the kernel may accept the first writes; bounded
            transport.write(b"\x00hello\x00" * 100)
    assert not transport.is_open


def test_a_pty_is_opened_exclusively():
    with MockNodeServer([make_scenario()], kind="pty") as server:
        url = server.urls["node-01"]
        with NodeClient(url) as first:
            with pytest.raises(PortVanished):
                NodeClient(url)
            assert first.status().boot_id == server.runners["node-01"].node.boot_id


def test_paced_transfer_takes_the_uart_line_time():
    with MockNodeServer([make_scenario(n_samples=1000)], kind="pty", pace=True, baud=230400) as server:
        with NodeClient(server.urls["node-01"], timeout_s=1.0) as c:
            measurement = c.acquire(baseline=False)
            started = time.monotonic()
            transfer = c.read_traces(measurement.measurement_id)
            elapsed_s = time.monotonic() - started
    payload_bytes = transfer.codes.nbytes  # 16 x 1000 x 2 = 32000
    line_s = payload_bytes / 23040.0
    assert line_s <= elapsed_s < 1.5 * line_s + 0.5


@contextlib.contextmanager
def _mock_node_cli(link_dir: Path, nodes: int) -> Iterator[subprocess.Popen]:
    """``python -m mocknode`` serving ``nodes`` nodes with their links in ``link_dir``; killed if still running."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "mocknode", "--nodes", str(nodes), "--link-dir", str(link_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO, env=env)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()


@pytest.mark.e2e
def test_cli_stops_cleanly_on_a_sigterm_sent_the_moment_a_port_is_announced(tmp_path):
    # A supervisor may stop the mock node as soon as it reads a port line; the ports are announced
    # while the server is built, so the handlers must already be in place (they were not: killed
    # by the signal, links left behind).
    with _mock_node_cli(tmp_path, 3) as proc:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not select.select([proc.stdout], [], [], 0.1)[0]:
            pass
        assert os.read(proc.stdout.fileno(), 4096).startswith(b"node-01 ")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert list(tmp_path.iterdir()) == []
        assert b"Traceback" not in proc.stderr.read()


@pytest.mark.e2e
def test_cli_serves_several_nodes_and_exits_cleanly_on_sigterm(tmp_path):
    with _mock_node_cli(tmp_path, 2) as proc:
        output = b""
        deadline = time.monotonic() + 10.0
        while output.count(b"\n") < 2 and time.monotonic() < deadline:
            if select.select([proc.stdout], [], [], 0.5)[0]:
                output += os.read(proc.stdout.fileno(), 4096)
        ports = dict(line.split() for line in output.decode().splitlines())
        assert sorted(ports) == ["node-01", "node-02"]
        with NodeClient(str(tmp_path / "node-02"), timeout_s=1.0) as c:
            assert c.info().node_id == "node-02"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        assert not (tmp_path / "node-01").exists()
