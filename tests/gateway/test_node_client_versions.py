"""NodeClient and the protocol's version step, BUSY and capabilities, against the mock node on a real pty."""
from __future__ import annotations

import numpy as np
import pytest

from gateway.node_client import NodeClient
from gateway.node_errors import CapabilityMissing, NodeTimeout
from mocknode.faults import FaultSpec
from mocknode.scenario import FirmwareSpec, NodeScenario, default_scenario
from mocknode.server import MockNodeServer

pytestmark = pytest.mark.timeout(60)


def scenario(faults: dict | None = None, firmware: dict | None = None) -> NodeScenario:
    return default_scenario(1).nodes[0].model_copy(
        update={"faults": FaultSpec(**(faults or {})), "firmware": FirmwareSpec(**(firmware or {}))})


def client_for(url: str, **kwargs) -> NodeClient:
    return NodeClient(url, **{"timeout_s": 0.5, "retries": 4, "backoff_s": 0.01, "backoff_max_s": 0.05,
                              "seed": 3, **kwargs})


def test_a_version_2_host_talks_version_1_to_a_version_1_node_and_reads_exact_records():
    with MockNodeServer([scenario({"protocol_version": 1})]) as server:
        runner = server.runners["node-01"]
        with client_for(runner.url) as client:
            info = client.info()
            assert (client.version, info.protocol_version, info.version_min) == (1, 1, None)
            client.configure(75e3, 5, 4, 3000)
            acquired = client.acquire(baseline=True)
            transfer = client.read_traces(acquired.measurement_id)
            assert acquired.averaging is None and transfer.averaging is None  # version 1 does not say
            np.testing.assert_array_equal(transfer.codes, runner.node.stored_codes(acquired.measurement_id))
            di = client.read_di(client.compute_di(client.acquire(baseline=False).measurement_id).di_id)
            assert di.pixels.shape == (201, 180)


def test_a_version_2_session_states_the_settings_of_every_record():
    with MockNodeServer([scenario()]) as server, client_for(server.urls["node-01"]) as client:
        client.configure(75e3, 4, 3, 2500, channels=[0, 2])
        acquired = client.acquire(baseline=False)
        transfer = client.read_traces(acquired.measurement_id, channels=[2], start=100, count=10)
    assert client.version == 2
    assert (acquired.excitation_hz, acquired.cycles, acquired.averaging, acquired.n_samples) == (75e3, 4, 3, 2500)
    assert (transfer.record_channels, transfer.record_n_samples, transfer.averaging) == ((0, 2), 2500, 3)


def test_busy_replies_are_retried_for_every_command_bulk_reads_included():
    with MockNodeServer([scenario({"busy_probability": 0.5})]) as server:
        runner = server.runners["node-01"]
        with client_for(runner.url, retries=12) as client:
            baseline = client.acquire(baseline=True)
            current = client.acquire(baseline=False)
            transfer = client.read_traces(current.measurement_id)
            di = client.read_di(client.compute_di(current.measurement_id).di_id)
            assert client.busy_replies > 0
    np.testing.assert_array_equal(transfer.codes, runner.node.stored_codes(current.measurement_id))
    assert (baseline.measurement_id, current.measurement_id) == (1, 2) and di.pixels.size == 201 * 180


def test_a_node_busy_on_every_attempt_ends_in_a_timeout_that_says_so():
    with MockNodeServer([scenario({"busy_probability": 0.999999})]) as server:
        with client_for(server.urls["node-01"], retries=2) as client:
            client.info()
            with pytest.raises(NodeTimeout, match="BUSY 3 times"):
                client.read_traces(1)


def test_commands_of_an_absent_capability_are_refused_before_anything_is_sent():
    with MockNodeServer([scenario(firmware={"capabilities": ["chunk_retransmit"]})]) as server:
        with client_for(server.urls["node-01"]) as client:
            current = client.acquire(baseline=False)
            sent_before = client._channel.seq
            for call in (lambda: client.compute_di(current.measurement_id), lambda: client.read_di(1),
                         lambda: client.acquire(baseline=True)):
                with pytest.raises(CapabilityMissing):
                    call()
            assert client._channel.seq == sent_before


def test_lost_chunks_from_a_node_without_chunk_retransmission_are_recovered_by_whole_rereads():
    faults = {"drop_byte_rate": 2e-5}
    with MockNodeServer([scenario(faults, {"capabilities": ["on_board_di", "baseline_slot"]})]) as server:
        runner = server.runners["node-01"]
        with client_for(runner.url, transfer_rounds=8) as client:
            acquired = client.acquire(baseline=False)
            transfer = client.read_traces(acquired.measurement_id)
    np.testing.assert_array_equal(transfer.codes, runner.node.stored_codes(acquired.measurement_id))
    assert transfer.chunks_rerequested > 0
