"""The DI map: the fast production path agrees with Algorithm 1 as printed, on any geometry."""

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imaging.dimap import BaselineMismatch, compute_di_map, default_window_samples, literal_di_map
from imaging.grid import Grid
from tests.support.synthetic import baseline_and_scatterer, measurement


@st.composite
def random_pair(draw):
    n_rx = draw(st.integers(1, 6))
    n_samples = draw(st.integers(50, 900))
    rx = np.array(draw(st.lists(st.floats(0, 359.999), min_size=n_rx, max_size=n_rx)))
    fs = draw(st.floats(2e5, 2e7))
    geometry = dict(
        fs_hz=fs,
        t0_s=draw(st.floats(-2e-4, 2e-4)),
        tx_rx_distance_mm=draw(st.floats(20, 800)),
        circumference_mm=draw(st.floats(50, 1500)),
        velocity_m_s=draw(st.floats(1000, 6000)),
        excitation_hz=draw(st.floats(2e4, 3e5)),
        cycles=draw(st.integers(1, 10)),
    )
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3]))
    b = (rng.standard_normal((n_rx, n_samples)) * scale).astype(np.float32)
    c = (b + rng.standard_normal((n_rx, n_samples)) * scale * draw(st.sampled_from([1e-4, 0.1, 1.0]))).astype(np.float32)
    grid = Grid(
        draw(st.floats(-50, 50)),
        draw(st.floats(0.5, 40)),
        draw(st.integers(1, 12)),
        draw(st.floats(0, 359)),
        draw(st.floats(0.5, 30)),
        draw(st.integers(1, 12)),
    )
    window = draw(st.one_of(st.none(), st.integers(1, 1200)))
    return measurement(b, rx, **geometry), measurement(c, rx, **geometry), grid, window


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_pair())
def test_fast_map_matches_literal_algorithm_1(pair):
    baseline, current, grid, window = pair
    fast = compute_di_map(baseline, current, grid, window_samples=window).pixels
    literal = literal_di_map(baseline, current, grid, window_samples=window)
    assert fast.shape == literal.shape == grid.shape
    np.testing.assert_allclose(fast, literal, rtol=1e-9, atol=0)


def test_quiet_window_after_loud_arrival_keeps_relative_accuracy():
    # A residual of 1e4 early and 1e-3 late: plain float64 prefix sums would lose the late windows.
    n = 3000
    b = np.zeros((1, n), np.float32)
    c = np.zeros((1, n), np.float32)
    c[0, 100:200] = 1e4
    c[0, 2000:2600] = 1e-3 * np.sin(np.arange(600))
    base, cur = measurement(b, np.array([0.0])), measurement(c, np.array([0.0]))
    grid = Grid(0, 10, 41, 0, 30, 12)
    np.testing.assert_allclose(
        compute_di_map(base, cur, grid).pixels, literal_di_map(base, cur, grid), rtol=1e-9, atol=0
    )


def test_window_past_the_end_counts_only_recorded_samples():
    # t0 so late that every window starts before sample 0: only the overlap with the record counts.
    b = np.zeros((1, 100), np.float32)
    c = np.ones((1, 100), np.float32)
    base, cur = measurement(b, np.array([0.0]), t0_s=1.0), measurement(c, np.array([0.0]), t0_s=1.0)
    assert compute_di_map(base, cur, Grid(0, 1, 3, 0, 90, 4), window_samples=10).pixels.max() == 0.0
    late = measurement(c, np.array([0.0]), t0_s=(400.0 / 3130e3) - 95 / 10e6)
    base_late = measurement(b, np.array([0.0]), t0_s=late.t0_s)
    px = compute_di_map(base_late, late, Grid(0, 1, 1, 0, 1, 1), window_samples=10).pixels
    assert px[0, 0] == pytest.approx(5.0)  # window starts at sample 95: 5 samples inside the record


def test_default_window_is_the_excitation_length():
    base, _ = baseline_and_scatterer(200, 90)
    assert default_window_samples(base) == round(5 / 85e3 * 10e6)


def test_default_grid_is_one_mm_by_one_degree():
    base, cur = baseline_and_scatterer(200, 90)
    di = compute_di_map(base, cur)
    assert di.pixels.shape == (401, 360)
    assert di.grid.axial_mm[-1] == 400.0 and di.grid.angle_deg[-1] == 359.0


def test_identical_measurements_give_an_all_zero_map():
    base, _ = baseline_and_scatterer(200, 90)
    assert compute_di_map(base, base).peak_di == 0.0


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(fs_hz=5e6), "fs_hz"),
        (dict(tx_rx_distance_mm=300.0), "tx_rx_distance_mm"),
        (dict(rx_angles_deg=np.arange(16) * 22.5 + 1), "receiver angles"),
    ],
)
def test_mismatched_baseline_is_refused(change, message):
    base, cur = baseline_and_scatterer(200, 90)
    with pytest.raises(BaselineMismatch, match=message):
        compute_di_map(base, dataclasses.replace(cur, **change))


def test_different_record_lengths_are_refused():
    base, cur = baseline_and_scatterer(200, 90)
    short = measurement(cur.traces[:, :5000], cur.rx_angles_deg)
    with pytest.raises(BaselineMismatch, match="shape"):
        compute_di_map(base, short)
