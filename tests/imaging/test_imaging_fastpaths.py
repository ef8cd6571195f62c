"""Every fast path of the imaging equals its literal oracle: compiled kernels, local maps, echo fit, resampling."""
import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import interpolate as sp_interpolate
from scipy import signal as sp_signal
from test_imaging_multipath import assert_equals_the_literal_map, random_problem

import imaging.multipath as multipath
from imaging import fitkernels, gather
from imaging.arrivals import analytic_matched, analytic_signal, hann_burst, matched_filter, reference_amplitude
from imaging.echofit import (
    _partial_products,
    burst_pair,
    fit_echoes,
    fit_smooth_echoes,
    literal_fit_echoes,
    literal_fit_smooth_echoes,
)
from imaging.grid import Grid
from imaging.multidefect import find_defects
from imaging.multipath import literal_multipath_pixels, local_multipath_pixels, multipath_pixels, path_model_for
from imaging.resample import Resampler
from imaging.scene import Scene
from tests.support.synthetic import baseline_and_scatterers, measurement

needs_numba = pytest.mark.skipif(not gather.compiled(), reason="numba is not installed")


@needs_numba
@settings(max_examples=60, deadline=None)
@given(st.data())
def test_compiled_gather_equals_the_numpy_gather(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    n_groups, n_axial, n_angle = data.draw(st.integers(1, 4)), data.draw(st.integers(1, 6)), data.draw(st.integers(1, 9))
    n_paths, n = data.draw(st.integers(0, 6)), data.draw(st.integers(1, 50))
    coherent = data.draw(st.booleans())
    row = rng.standard_normal(n + 1) + (1j * rng.standard_normal(n + 1) if coherent else 0)
    row = row.astype(np.complex64 if coherent else np.float32)
    groups = rng.integers(0, n_groups, n_paths).astype(np.int64)
    idx = rng.integers(0, n + 1, (n_paths, n_axial * n_angle)).astype(np.int32)
    w = rng.random((n_paths, n_axial * n_angle)).astype(np.float32)
    roll = data.draw(st.integers(0, 3 * n_angle))
    start = (rng.standard_normal((n_groups, n_axial, n_angle)) * (1 + 1j if coherent else 1)).astype(row.dtype)
    fast, slow = start.copy(), start.copy()
    gather.accumulate_compiled(fast, row, groups, idx, w, roll)
    gather.accumulate_numpy(slow, row, groups, idx, w, roll)
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-5)


@needs_numba
@settings(max_examples=40, deadline=None)
@given(st.data())
def test_compiled_echo_fit_sums_equal_the_numpy_sums(data):
    # Columns starting before, inside, across the end of and after a short record, some invalid.
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    shapes, table = _partial_products(1e6, 85e3, 5)
    size = shapes.shape[1]
    n_rx, n_cols, n_pos = data.draw(st.integers(1, 4)), data.draw(st.integers(1, 12)), data.draw(st.integers(1, 3))
    n = data.draw(st.integers(1, 3 * size))
    starts = rng.integers(-size - 2, n + 2, (n_rx, n_cols)).astype(np.int64)
    kind = rng.integers(0, 2, (n_rx, n_cols)).astype(np.int64)
    valid = (rng.random((n_rx, n_cols)) > 0.2) & (starts < n) & (starts + size > 0)  # as the fit sets it
    residual = rng.standard_normal((n_rx, n))
    fast = fitkernels.normal_equations(residual, starts, kind, valid, shapes, table)
    slow = fitkernels.normal_equations_numpy(residual, starts, kind, valid, shapes, table)
    for f, s in zip(fast, slow, strict=True):
        np.testing.assert_allclose(f, s, rtol=1e-12, atol=1e-12)
    coef, owner = rng.standard_normal((n_rx, n_cols)), rng.integers(0, n_pos, (n_rx, n_cols)).astype(np.int64)
    np.testing.assert_allclose(fitkernels.synthesise(coef, starts, kind, valid, owner, shapes, n_pos, n),
                               fitkernels.synthesise_numpy(coef, starts, kind, valid, owner, shapes, n_pos, n),
                               rtol=1e-12, atol=1e-12)


@needs_numba
@settings(max_examples=40, deadline=None)
@given(st.data())
def test_compiled_group_columns_equal_the_fft_convolution(data):
    # Paths starting before, inside, across the end of and after a short record, several to a group,
    # with and without a carrier shift.
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    shapes = np.stack(burst_pair(1e6, 85e3, 5))
    size = shapes.shape[1]
    n_rx, n_pos, n_groups = data.draw(st.integers(1, 3)), data.draw(st.integers(1, 2)), data.draw(st.integers(1, 4))
    n, n_paths = data.draw(st.integers(1, 3 * size)), data.draw(st.integers(0, 30))
    rx, pos, group = (rng.integers(0, k, n_paths) for k in (n_rx, n_pos, n_groups))
    starts = rng.integers(-size + 1, n, n_paths)  # as group_waves keeps them: overlapping the record
    c = rng.standard_normal(n_paths)
    s = rng.standard_normal(n_paths) if data.draw(st.booleans()) else None
    out_shape = (n_rx, n_pos, n_groups, n)
    fast = fitkernels.group_columns(rx, pos, group, starts, c, s, shapes, out_shape)
    slow = fitkernels.group_columns_numpy(rx, pos, group, starts, c, s, shapes, out_shape)
    assert fast.shape == slow.shape == (n_rx, n_pos, n_groups, 2, n)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12 * max(1.0, float(np.abs(c).sum())))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_problem())
def test_numpy_fallback_map_matches_the_literal_sum(problem):
    feature, scene, normalise = problem
    original = multipath.accumulate
    multipath.accumulate = gather.accumulate_numpy
    try:
        fast = multipath_pixels(feature, scene, normalise=normalise)
    finally:
        multipath.accumulate = original
    assert_equals_the_literal_map(fast, feature, scene, normalise)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_problem(), st.booleans())
def test_local_map_matches_the_literal_sum(problem, compiled):
    feature, scene, normalise = problem
    local = local_multipath_pixels(feature, scene, normalise=normalise, compiled=compiled)
    literal = literal_multipath_pixels(feature, scene, normalise=normalise)
    np.testing.assert_allclose(local, literal, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(literal).max())))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_echo_fit_equals_the_literal_fit(data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    ends = data.draw(st.booleans())
    n_samples = data.draw(st.sampled_from([1500, 3000, 6000]))
    base, _ = baseline_and_scatterers([], n_samples=n_samples)
    if ends:  # end paths: long arrivals the record's end cuts
        base = measurement(base.traces, base.rx_angles_deg, pipe_length_mm=1000.0, tx_axial_mm=300.0)
    model = path_model_for(base, model_ends=ends)
    positions = [(data.draw(st.floats(-20, 420)), data.draw(st.floats(0, 360)))
                 for _ in range(data.draw(st.integers(1, 3)))]
    scene = Scene.of(base, model, rx_mask=rng.random(base.n_rx) > 0.2)
    residual = rng.standard_normal(base.traces.shape)
    fast = fit_echoes(residual, scene, positions)
    slow = literal_fit_echoes(residual, scene, positions)
    scale = max(float(np.abs(sum(slow)).max()), 1e-12)
    # The total fit is a projection (unique); the split between positions is unique unless two
    # positions' columns (nearly) coincide, where either solver's minimum-norm split is rounding.
    np.testing.assert_allclose(sum(fast), sum(slow), rtol=0, atol=1e-7 * scale)


def test_echo_fit_split_equals_the_literal_split_for_distinct_positions():
    base, cur = baseline_and_scatterers([(120.0, 60.0, 0.05), (290.0, 230.0, 0.04)], noise_rms=5e-4, seed=2)
    scene = Scene.of(base, path_model_for(base))
    residual = base.traces.astype(np.float64) - cur.traces
    positions = [(120.0, 60.0), (290.0, 230.0)]
    for fast, slow in zip(fit_echoes(residual, scene, positions), literal_fit_echoes(residual, scene, positions), strict=True):
        np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-9 * float(np.abs(slow).max()))



@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_smooth_echo_fit_equals_the_literal_fit(data):
    # Each path's amplitude a circular harmonic of the receiver's bearing up to ``orders``: the
    # block-structured normal equations against every unknown's column written out in full.
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    ends = data.draw(st.booleans())
    base, _ = baseline_and_scatterers([], n_samples=data.draw(st.sampled_from([1500, 3000])))
    if ends:
        base = measurement(base.traces, base.rx_angles_deg, pipe_length_mm=1000.0, tx_axial_mm=300.0)
    positions = [(data.draw(st.floats(-20, 420)), data.draw(st.floats(0, 360)))
                 for _ in range(data.draw(st.integers(1, 2)))]
    orders = data.draw(st.integers(0, 2))
    model = dataclasses.replace(path_model_for(base, model_ends=ends), wraps=data.draw(st.sampled_from([2, 6])))
    scene = Scene.of(base, model, rx_mask=rng.random(base.n_rx) > 0.2)
    residual = rng.standard_normal(base.traces.shape)
    fast = fit_smooth_echoes(residual, scene, positions, orders=orders)
    slow = literal_fit_smooth_echoes(residual, scene, positions, orders=orders)
    scale = max(float(np.abs(sum(slow)).max()), 1e-12)
    np.testing.assert_allclose(sum(fast), sum(slow), rtol=0, atol=1e-7 * scale)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-5e-3, 5e-3))
def test_bspline_resampler_matches_a_cubic_spline_inside_the_record(seed, stretch):
    rng = np.random.default_rng(seed)
    t = np.arange(2000) / 10e6
    # A band-limited record like ours: bursts at 85 kHz, sampled at 10 MHz.
    traces = np.stack([np.convolve(rng.standard_normal(2000), np.hanning(118) * np.sin(np.arange(118) * 2 * np.pi / 118),
                                   mode="same") for _ in range(3)])
    m = measurement(traces.astype(np.float32), np.array([0.0, 120.0, 240.0]))
    reference = sp_interpolate.CubicSpline(t, m.traces.astype(np.float64), axis=1)
    at = t[20:-20] / (1 + stretch)
    np.testing.assert_allclose(Resampler(m)(at), reference(at), rtol=0, atol=1e-6 * float(np.abs(traces).max()))
    outside = np.array([-1e-6, t[-1] + 1e-6])
    assert np.all(Resampler(m)(outside) == 0.0)


def test_coarse_to_fine_search_finds_the_peak_of_the_full_fine_map():
    base, cur = baseline_and_scatterers([(210.0, 135.0, 0.05)], noise_rms=1e-3, seed=11)
    scene = Scene.of(base, path_model_for(base), reference_amplitude_v=reference_amplitude(base))
    residual = base.traces.astype(np.float64) - cur.traces
    coarse = find_defects(residual, scene.with_grid(Grid.default(400.0, 4.0, 4.0)), threshold=0.0, max_defects=1)[2]
    fine = find_defects(residual, scene.with_grid(Grid.default(400.0, 1.0, 1.0)), threshold=0.0, max_defects=1)[2]
    assert abs(coarse.axial_mm - fine.axial_mm) < 0.5 and abs(coarse.angle_deg - fine.angle_deg) < 0.5
    assert coarse.di == pytest.approx(fine.di, rel=1e-5)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.integers(1, 3))
def test_analytic_signal_equals_scipy_hilbert(seed, n, rows):
    x = np.random.default_rng(seed).standard_normal((rows, n))
    np.testing.assert_allclose(analytic_signal(x), sp_signal.hilbert(x), rtol=0, atol=1e-12 * max(1.0, np.abs(x).max()))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-5e-3, 5e-3), st.integers(2, 400))
def test_compiled_resampler_equals_its_numpy_fallback(seed, stretch, n):
    rng = np.random.default_rng(seed)
    m = measurement(rng.standard_normal((3, n)).astype(np.float32), np.array([0.0, 120.0, 240.0]))
    # Inside, on both ends, and outside the record.
    at = np.concatenate([np.arange(-2, n + 2) / 10e6 / (1 + stretch), rng.uniform(-1e-6, (n + 1) / 10e6, 50)])
    resampler = Resampler(m)
    np.testing.assert_allclose(resampler(at), resampler(at, compiled=False), rtol=0,
                               atol=1e-12 * float(np.abs(m.traces).max()))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2400, 6000))
def test_one_pass_analytic_correlation_equals_hilbert_of_the_correlation_away_from_the_ends(seed, n):
    rng = np.random.default_rng(seed)
    burst = hann_burst(10e6, 85e3, 5)
    # A record like ours: bursts at 85 kHz in noise, zero-mean.
    x = rng.standard_normal((2, n)) * 0.01
    for k in rng.integers(burst.size, n - 2 * burst.size, 3):
        x[:, k:k + burst.size] += rng.uniform(0.2, 1.0) * burst
    two_pass = analytic_signal(matched_filter(x, burst))
    one_pass = analytic_matched(x, burst)
    inner = slice(burst.size, n - burst.size)
    np.testing.assert_allclose(one_pass[:, inner], two_pass[:, inner], rtol=0, atol=2e-3 * np.abs(two_pass).max())
    np.testing.assert_allclose(one_pass.real, two_pass.real, rtol=0, atol=1e-9 * np.abs(two_pass).max())
