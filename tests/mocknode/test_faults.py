"""Every injected fault ends in a typed error or a successful retry: never a hang, never a wrong result."""
from __future__ import annotations

import time

import numpy as np
import pytest

from gateway.node_client import NodeClient
from gateway.node_errors import NodeError, NodeTimeout, ProtocolMismatch, TransferError
from mocknode.faults import FaultSpec
from mocknode.scenario import NodeScenario, default_scenario
from mocknode.server import MockNodeServer
from nodelink.transport import PortVanished
from protocol.messages import ErrorCode
from tests.support.clocks import ManualClock

pytestmark = pytest.mark.timeout(30)


def make_scenario(**faults) -> NodeScenario:
    return default_scenario(1).nodes[0].model_copy(update={"faults": FaultSpec(**faults)})


def serve(kind: str = "pty", link_dir=None, clock=time.monotonic, **faults) -> MockNodeServer:
    return MockNodeServer([make_scenario(**faults)], kind=kind, link_dir=link_dir, clock=clock)


def quick_client(url: str, **kwargs) -> NodeClient:
    options = {"timeout_s": 0.3, "retries": 4, "backoff_s": 0.01, "backoff_max_s": 0.05, "seed": 1}
    return NodeClient(url, **{**options, **kwargs})


@pytest.mark.parametrize("kind, fault", [("pty", "corrupt_byte_rate"), ("tcp", "drop_byte_rate")])
def test_line_errors_end_in_an_exact_transfer_rerequesting_only_lost_chunks(kind, fault):
    with serve(kind, **{fault: 5e-5}) as server:
        runner = server.runners["node-01"]
        with quick_client(runner.url) as client:
            acquired = client.acquire(baseline=False)
            retried_before = client.retried
            transfer = client.read_traces(acquired.measurement_id)
            np.testing.assert_array_equal(transfer.codes, runner.node.stored_codes(acquired.measurement_id))
            assert 0 < transfer.chunks_rerequested < 94  # 16 x 6000 int16 = 94 chunks of 2048 B
            assert client.frame_errors > 0
            # Chunks asked again are retries (pipesentry_gateway_node_retries_total says so); they were not counted.
            assert client.retried - retried_before >= transfer.chunks_rerequested


def test_a_line_too_noisy_for_any_frame_ends_in_node_timeout():
    with serve(corrupt_byte_rate=0.05) as server, quick_client(server.urls["node-01"], retries=2) as client:
        started = time.monotonic()
        with pytest.raises(NodeTimeout):
            client.status()
        assert time.monotonic() - started < 3 * 0.3 + 1.0


def test_chunks_that_keep_getting_lost_end_in_transfer_error():
    with serve(drop_byte_rate=2e-3) as server, quick_client(server.urls["node-01"], transfer_rounds=1) as client:
        acquired = client.acquire(baseline=False)
        with pytest.raises(TransferError):
            client.read_traces(acquired.measurement_id)


def test_a_node_that_always_stalls_ends_in_node_timeout():
    with serve(stall_probability=1.0, stall_s=0.2) as server, quick_client(server.urls["node-01"], retries=2) as c:
        with pytest.raises(NodeTimeout):
            c.info()


def test_stalls_are_survived_by_retries_and_each_acquisition_runs_once():
    with serve(stall_probability=0.5, stall_s=0.25) as server:
        with quick_client(server.urls["node-01"], timeout_s=0.15, retries=10) as client:
            ids = [client.acquire(baseline=False).measurement_id for _ in range(3)]
            status = client.status()
            assert client.retried > 0
    assert ids == [1, 2, 3] and status.n_measurements == 3


@pytest.mark.parametrize("kind", ["pty", "tcp"])
def test_disconnect_is_port_vanished_and_reopen_reaches_the_rebooted_node(kind, tmp_path):
    clock = ManualClock()  # the node's time: the disconnect comes when the test says, not after a sleep
    with serve(kind, link_dir=tmp_path, clock=clock, disconnect_every_s=600.0, reconnect_after_s=30.0) as server:
        runner = server.runners["node-01"]
        url = str(tmp_path / "node-01") if kind == "pty" else runner.url
        with quick_client(url) as client:
            first_boot = client.info().boot_id
            assert [client.status().boot_id for _ in range(3)] == [first_boot] * 3  # not yet: the clock stands
            clock.advance(600.0)
            deadline = time.monotonic() + 5.0
            with pytest.raises(PortVanished):
                for _ in range(100_000):
                    assert time.monotonic() < deadline, "the port never vanished"
                    client.status()
            assert not runner.wait_for_generation(2, timeout_s=0.2)  # unplugged for reconnect_after_s of node time
            clock.advance(30.0)
            assert runner.wait_for_generation(2, timeout_s=5.0)
            client.reopen()
            info = client.info()
    assert info.boot_id != first_boot and info.node_id == "node-01"


def test_reboot_mid_transfer_is_a_typed_error_and_the_node_state_is_gone():
    with serve(reboot_probability=0.2, garbage_on_power_up=200) as server:
        with quick_client(server.urls["node-01"]) as client:
            first_boot = client.info().boot_id
            acquired = client.acquire(baseline=True)
            with pytest.raises(NodeError) as caught:
                client.read_traces(acquired.measurement_id)
            assert caught.value.code == ErrorCode.NO_SUCH_MEASUREMENT
            status = client.status()
    assert status.boot_id != first_boot and not status.baseline_stored


def test_garbage_on_power_up_is_skipped():
    with serve(garbage_on_power_up=5000) as server, quick_client(server.urls["node-01"]) as client:
        assert client.info().node_id == "node-01"


def test_a_node_with_another_protocol_version_is_a_protocol_mismatch():
    with serve(protocol_version=3) as server, quick_client(server.urls["node-01"]) as client:
        with pytest.raises(ProtocolMismatch):
            client.info()
        with pytest.raises(ProtocolMismatch):
            client.status()


def test_stopping_the_server_under_a_connected_client_is_port_vanished():
    server = serve().start()
    client = quick_client(server.urls["node-01"])
    try:
        assert client.status().n_measurements == 0
        server.stop()
        with pytest.raises(PortVanished):
            client.status()
    finally:
        client.close()
        server.stop()
