"""Receiver faults of the mock node (scenario ``receiver_faults``): a transducer that dies, loses
coupling or moves, for a while — and what the imaging's health check makes of it."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from imaging.health import check_receivers
from mocknode.physics import acquire, simulate_volts
from mocknode.scenario import AcquisitionSpec, NodeScenario, ReceiverFaultSpec

QUIET = AcquisitionSpec(noise_v_rms=0.0, direct_amplitude_v=0.1, adc_full_scale_v=0.5)
NOISY = AcquisitionSpec()  # the node's default receiver noise


def node(*faults: ReceiverFaultSpec, acquisition: AcquisitionSpec = QUIET) -> NodeScenario:
    return NodeScenario(node_id="t", acquisition=acquisition, receiver_faults=list(faults))


def volts(scn: NodeScenario, elapsed_s: float = 0.0) -> np.ndarray:
    return simulate_volts(scn, elapsed_s=elapsed_s, temperature_c=20.0, rng=np.random.default_rng(0),
                          include_noise=False)


def test_a_faulty_receiver_keeps_its_gain_of_the_signal_and_the_others_are_untouched():
    healthy = volts(node())
    faulty = volts(node(ReceiverFaultSpec(rx_index=3, gain=0.3)))
    np.testing.assert_allclose(faulty[3], 0.3 * healthy[3], rtol=1e-12, atol=1e-15)
    others = np.arange(16) != 3
    np.testing.assert_array_equal(faulty[others], healthy[others])


def test_a_fault_is_active_only_in_its_time_window():
    scn = node(ReceiverFaultSpec(rx_index=5, gain=0.0, from_s=10.0, until_s=20.0))
    healthy = volts(node())
    assert np.array_equal(volts(scn, 9.9), healthy)
    assert not np.any(volts(scn, 10.0)[5]) and not np.any(volts(scn, 19.9)[5])
    assert np.array_equal(volts(scn, 20.0), healthy)


def test_a_delay_moves_the_channels_arrival_by_that_much():
    fs = QUIET.fs_hz
    delay_s = 40 / fs  # 40 samples, exactly
    healthy = volts(node())[2]
    moved = volts(node(ReceiverFaultSpec(rx_index=2, gain=1.0, delay_s=delay_s)))[2]
    np.testing.assert_allclose(moved[40:], healthy[:-40], atol=1e-12)
    assert np.argmax(np.abs(moved)) - np.argmax(np.abs(healthy)) == 40


@pytest.mark.parametrize(
    ("fault", "kind"),
    [
        (ReceiverFaultSpec(rx_index=4, gain=0.02), "no_signal"),
        (ReceiverFaultSpec(rx_index=4, gain=0.3), "amplitude"),
        (ReceiverFaultSpec(rx_index=4, gain=1.0, delay_s=5e-6), "timing"),  # ~0.4 period at 85 kHz
    ],
)
def test_the_imaging_health_check_names_the_fault_the_node_simulates(fault, kind):
    baseline = acquire(node(acquisition=NOISY), 0.0, np.random.default_rng(1)).to_measurement(node(acquisition=NOISY))
    scn = node(fault, acquisition=NOISY)
    current = acquire(scn, 0.0, np.random.default_rng(2)).to_measurement(scn)
    faults = check_receivers(baseline, current)
    assert [(f.rx_index, f.kind) for f in faults] == [(4, kind)]


def test_a_fault_on_a_receiver_the_ring_does_not_have_is_refused():
    with pytest.raises(ValidationError, match="the ring has 16 receivers"):
        node(ReceiverFaultSpec(rx_index=16))
    with pytest.raises(ValidationError, match="until_s must be after from_s"):
        node(ReceiverFaultSpec(rx_index=1, from_s=5.0, until_s=5.0))


def test_a_scenario_file_declares_receiver_faults_per_node(tmp_path):
    from mocknode.scenario import load_scenario

    path = tmp_path / "s.toml"
    path.write_text('[[nodes]]\nnode_id = "n1"\n[[nodes.receiver_faults]]\nrx_index = 3\nfrom_s = 30\n')
    fault, = load_scenario(path).nodes[0].receiver_faults
    assert (fault.rx_index, fault.gain, fault.from_s, fault.until_s) == (3, 0.0, 30.0, None)
