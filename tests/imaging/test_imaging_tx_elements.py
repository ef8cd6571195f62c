"""A sparse Tx ring, element by element: when order N propagates, what it adds, and that the map then finds a
strong scatterer on independent full-wave physics where the plane-wave model cannot."""
import dataclasses
import math

import numpy as np
import pytest

from fullwave.defects import Mass, Notch
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging import gather, multidefect
from imaging.analysis import analyze
from imaging.arrivals import analytic_noise_correlation, end_reflection_coefficients, hann_burst, reference_amplitude
from imaging.dimap import DIMap
from imaging.echofit import FIT_RCOND, fit_echoes, fit_smooth_echoes, group_waves
from imaging.features import residual_feature
from imaging.grid import Grid
from imaging.localize import Estimate
from imaging.multipath import literal_multipath_pixels, local_multipath_pixels, multipath_pixels, path_model_for
from imaging.paths import PathModel, element_scattering_cosines, incident_terms, ring_order_cutoff_hz, sparse_ring
from imaging.pipeline import default_grid
from imaging.region import (
    CIRC_FLOOR_MM,
    RECEIVER_LEAN,
    RECEIVER_LEAN_WITH_ENDS,
    Region,
    receiver_lean,
    receiver_lean_mm,
)
from imaging.scene import Scene
from imaging.timing import surface_distance_mm

MID_WALL_MM = math.pi * (114.6 - 4.0)  # the paper's pipe, where the wave travels
C_MM_S = 3130.0e3
FS_HZ = 10e6


def _ring_model(n_elements: int, frequency_hz: float, **changes) -> PathModel:
    arcs = tuple(np.arange(n_elements) * MID_WALL_MM / n_elements)
    return PathModel(400.0, MID_WALL_MM, C_MM_S / frequency_hz, tx_arcs_mm=arcs, **changes)


def _incident_field(model: PathModel, axial_mm: float, arc_mm: float, frequency_hz: float, t_s: np.ndarray):
    """The modelled incident waveform at one point: every element image's burst, weighted, added."""
    burst = hann_burst(FS_HZ, frequency_hz, 5)
    field = np.zeros(t_s.size)
    family = model.families()[0]
    for length, weight in incident_terms(model, np.array(axial_mm), np.array(arc_mm), family):
        k = round(float(length) / C_MM_S * FS_HZ)
        if k < t_s.size:
            field[k:k + burst.size] += float(weight) * burst[: t_s.size - k]
    return field, burst


def test_eight_elements_launch_a_propagating_order_at_75_khz_and_sixteen_do_not_at_85_khz():
    assert ring_order_cutoff_hz(8, MID_WALL_MM, 3130.0) == pytest.approx(72.07e3, rel=1e-3)
    assert sparse_ring(8, MID_WALL_MM, 3130.0, 75e3, 5) and sparse_ring(8, MID_WALL_MM, 3130.0, 85e3, 5)
    assert not sparse_ring(16, MID_WALL_MM, 3130.0, 85e3, 5)  # order 16 cuts off at 144 kHz
    assert sparse_ring(16, MID_WALL_MM, 3130.0, 130e3, 5)  # inside a 130 kHz burst's band


def test_the_sum_of_a_dense_rings_elements_is_the_plane_wave_far_from_it():
    model = _ring_model(16, 85e3)
    t = np.arange(4000) / FS_HZ
    for arc in (0.0, 5.0, MID_WALL_MM / 32):  # on an element, near one, half-way between two
        field, burst = _incident_field(model, 300.0, arc, 85e3, t)
        start = round(300.0 / C_MM_S * FS_HZ)
        head = field[start - 200:start + burst.size + 200]
        plane = np.zeros(head.size)
        plane[200:200 + burst.size] = burst
        gain = float(np.max(np.abs(np.fft.ifft(np.fft.fft(head) * np.conj(np.fft.fft(plane)))))) / float(plane @ plane)
        assert gain == pytest.approx(1.0, abs=0.1)  # amplitude 1, whatever the angle
        tail = field[start + burst.size + 400:start + 5 * burst.size]
        assert float(tail @ tail) < 0.01 * float(head @ head)  # nothing follows it


def test_a_sparse_ring_trails_an_order_n_wave_that_varies_round_the_pipe():
    model = _ring_model(8, 75e3)
    t = np.arange(6000) / FS_HZ
    start = round(300.0 / C_MM_S * FS_HZ)
    spacing = MID_WALL_MM / 8
    tails, ratios = [], []
    for arc in (0.0, spacing / 4, spacing / 2):  # in line with an element, a quarter and half-way to the next
        field, burst = _incident_field(model, 300.0, arc, 75e3, t)
        head = field[start:start + burst.size]
        tail = field[start + burst.size + 200:]
        tails.append(tail)
        ratios.append(float(tail @ tail) / float(head @ head))
    on, _, half = tails
    assert ratios[0] > 0.5 and ratios[2] > 0.5  # order 8, slow near its cut-off: as much as the plane wave, later
    assert ratios[1] < 0.2 * ratios[0]  # cos(8 theta) = 0 a quarter of the way between elements
    assert float(on @ half) / math.sqrt(float(on @ on) * float(half @ half)) < -0.8  # and -1 half-way: not axisymmetric


def test_path_model_for_a_baseline_models_an_eight_ring_at_75_khz_by_its_elements():
    spec = SimulationSpec(pipe=PipeModel(length_mm=300.0), rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=200.0,
                                                                             n_transducers=8),
                          excitation_hz=75e3, cell_mm=2.0, n_samples=300)
    eight = simulate(spec)
    sixteen = simulate(spec.with_changes(rings=dataclasses.replace(spec.rings, n_transducers=16), excitation_hz=85e3))
    model = path_model_for(eight, wall_mm=4.0)
    assert model.elements and len(model.tx_arcs_mm) == 8
    assert model.tx_arcs_mm[1] == pytest.approx(MID_WALL_MM / 8, rel=1e-3)
    assert not path_model_for(eight, wall_mm=4.0, elements=False).elements
    assert not path_model_for(sixteen, wall_mm=4.0).elements


@pytest.mark.skipif(not gather.compiled(), reason="numba is not installed")
def test_compiled_coherent_energy_equals_the_numpy_sum():
    rng = np.random.default_rng(7)
    correlation = analytic_noise_correlation(FS_HZ, 75e3, 5)
    groups = rng.integers(0, 3, 12).astype(np.int64)
    idx = rng.integers(0, 900, (12, 40)).astype(np.int32)  # 900 = outside a record of 900 samples
    w = rng.random((12, 40)).astype(np.float32)
    fast = gather.coherent_energy(groups, idx, w, correlation, 3, 900)
    slow = gather.coherent_energy_numpy(groups, idx, w, correlation, 3, 900)
    np.testing.assert_allclose(fast, slow, rtol=1e-6)
    assert np.all(fast >= -1e-9)  # a variance


def _scene(model: PathModel, grid: Grid, n_rx: int = 8) -> Scene:
    return Scene(rx_angles_deg=np.arange(n_rx) * 360.0 / n_rx, rx_mask=np.ones(n_rx, bool), velocity_m_s=3130.0,
                 t0_s=0.0, fs_hz=FS_HZ, excitation_hz=75e3, cycles=5, window_samples=1, model=model, grid=grid)


def test_the_fast_and_local_maps_of_an_element_model_equal_the_literal_sum():
    model = _ring_model(8, 75e3, tx_images=1)
    grid = Grid(100.0, 20.0, 4, 0.0, 15.0, 24)  # a full ring: the receivers' tables are shared, rolled by 45 deg
    rng = np.random.default_rng(3)
    feature = rng.standard_normal((8, 3000)) + 1j * rng.standard_normal((8, 3000))
    scene = _scene(model, grid)
    literal = literal_multipath_pixels(feature, scene)
    np.testing.assert_allclose(multipath_pixels(feature, scene), literal, rtol=1e-4)
    np.testing.assert_allclose(local_multipath_pixels(feature, scene), literal, rtol=1e-9)


def test_noise_alone_scores_the_same_whether_the_ring_is_modelled_by_elements_or_as_a_plane_wave():
    # The plane-wave map projects on its groups jointly, the element model adds their powers: the
    # noise floor both are thresholded against must still be the same. Three noise records; the
    # 99th percentile (one record's maximum varied 0.92-1.21 between them).
    grid = default_grid("multipath", 400.0, np.arange(8) * 45.0)
    plane_scene, element_scene = (_scene(PathModel(400.0, MID_WALL_MM, C_MM_S / 75e3), grid),
                                  _scene(_ring_model(8, 75e3), grid))
    assert plane_scene.joint_groups
    plane, elements = [], []
    for seed in (11, 12, 13):
        noise = np.random.default_rng(seed).standard_normal((8, 6000))
        plane.append(multipath_pixels(residual_feature(noise, plane_scene), plane_scene))
        elements.append(multipath_pixels(residual_feature(noise, element_scene), element_scene))
    # The matched feature of white noise is correlated over a burst: only the pairwise energy keeps these near 1.
    assert np.median(elements) / np.median(plane) == pytest.approx(1.0, abs=0.1)
    assert np.percentile(elements, 99) / np.percentile(plane, 99) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("shared", [True, False])
def test_the_echo_fit_of_an_element_model_recovers_echoes_made_by_the_same_model(shared):
    model = _ring_model(8, 75e3, tx_images=1)
    scene = _scene(model, Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    n = 5000
    waves = group_waves(scene, [(180.0, 50.0)], n)[:, 0]  # [m, group, shape, n]
    rng = np.random.default_rng(5)
    amplitudes = rng.standard_normal(waves.shape[1:3])  # one per group and shape, the same on every receiver
    record = np.einsum("mgsn,gs->mn", waves, amplitudes)
    fitted = (fit_smooth_echoes(record, scene, [(180.0, 50.0)]) if shared else fit_echoes(record, scene, [(180.0, 50.0)]))
    assert float(np.sum((record - fitted[0]) ** 2)) < 1e-12 * float(np.sum(record**2))
    elsewhere = fit_smooth_echoes(record, scene, [(300.0, 230.0)])[0]
    assert float(np.sum((record - elsewhere) ** 2)) > 0.5 * float(np.sum(record**2))  # the wrong place explains little


def _dense_group_fit(record: np.ndarray, scene: Scene, positions: list, shared: bool) -> list[np.ndarray]:
    """The element model's fit written out over every column and sample: the oracle of the fit that leaves
    out what no record reaches."""
    waves = group_waves(scene, positions, record.shape[1])
    n_rx, n_pos = waves.shape[:2]
    columns = waves.reshape(n_rx, -1, record.shape[1])
    gram, rhs = columns @ columns.transpose(0, 2, 1), columns @ record[:, :, None]
    if not shared:
        coef = (np.linalg.pinv(gram, rtol=FIT_RCOND, hermitian=True) @ rhs)[:, :, 0]
    else:  # one amplitude per column, the same on every receiver (SMOOTH_ORDERS = 0)
        coef = np.broadcast_to(np.linalg.pinv(gram.sum(axis=0), rtol=FIT_RCOND, hermitian=True) @ rhs.sum(axis=0)[:, 0],
                               (n_rx, columns.shape[1]))
    fitted = np.einsum("mpan,mpa->mpn", waves.reshape(n_rx, n_pos, -1, record.shape[1]), coef.reshape(n_rx, n_pos, -1))
    return [fitted[:, p] for p in range(n_pos)]


@pytest.mark.parametrize("shared", [True, False])
def test_an_element_models_fit_leaves_out_what_no_record_reaches_and_fits_the_same(shared):
    # A short record: many of a position's path groups reach it on no receiver (zero columns), and no
    # echo reaches its first half. Left out, the fit is the written-out one's; a position none of
    # whose echoes reaches the record is fitted with nothing, alone or beside another.
    model = _ring_model(8, 75e3, tx_images=1, near_end_mm=-150.0, far_end_mm=550.0, near_reflection=1.0,
                        far_reflection=1.0)  # end echoes: the groups of paths by way of either end
    scene = _scene(model, Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    n, at = 2600, [(180.0, 50.0), (320.0, 200.0)]
    waves = group_waves(scene, at, n)
    assert 0.1 < float(np.mean(~np.any(waves, axis=(0, 4)))) < 0.9  # some columns reach no record
    record = np.einsum("mpgsn,pgs->mn", waves, np.random.default_rng(2).standard_normal(waves.shape[1:4]))
    record += 0.05 * float(np.std(record)) * np.random.default_rng(3).standard_normal(record.shape)
    fit = fit_smooth_echoes if shared else fit_echoes
    for got, want in zip(fit(record, scene, at), _dense_group_fit(record, scene, at, shared), strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * float(np.abs(record).max()))
    beyond = (-4000.0, 50.0)  # every echo arrives after the record ends
    assert not np.any(group_waves(scene, [beyond], n))
    assert not np.any(fit(record, scene, [beyond])[0])
    alone, beside = fit(record, scene, at[:1])[0], fit(record, scene, [at[0], beyond])
    np.testing.assert_allclose(beside[0], alone, rtol=0, atol=1e-9 * float(np.abs(record).max()))
    assert not np.any(beside[1])


def test_a_sparse_rings_defect_is_turned_to_the_angle_its_echoes_give_within_half_a_pitch():
    # Echoes of a scatterer at 180 mm 50 deg (one amplitude per path group, as the plain fit models
    # them); a defect placed at the right distance but 15 deg off, as the map's pull towards a
    # receiver leaves it, is turned back; one the axial fit did not place (no map_peak) is left alone.
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    waves = group_waves(scene, [(180.0, 50.0)], 5000)[:, 0]
    record = np.einsum("mgsn,gs->mn", waves, np.random.default_rng(7).standard_normal(waves.shape[1:3]))
    unexplained = multidefect._unexplained_by(multidefect._Search(record, scene), [])
    off = Estimate(180.0, 65.0, 0.1)
    placed = multidefect.Found(off, None, 0.0, map_peak=Estimate(190.0, 65.0, 0.1))  # type: ignore[arg-type]
    turned = multidefect._echo_fit_angle(placed, unexplained, scene.n_rx)
    assert turned.estimate.angle_deg == pytest.approx(50.0, abs=1.0) and turned.estimate.axial_mm == 180.0
    unplaced = multidefect.Found(off, None, 0.0)  # type: ignore[arg-type]
    assert multidefect._echo_fit_angle(unplaced, unexplained, scene.n_rx).estimate == off
    beyond = multidefect.Found(Estimate(180.0, 80.0, 0.1), None, 0.0, map_peak=off)  # type: ignore[arg-type]
    assert multidefect._echo_fit_angle(beyond, unexplained, scene.n_rx).estimate.angle_deg >= 80.0 - 22.5  # half a pitch at most


def test_a_path_straight_through_scatters_forward_and_every_angle_is_a_cosine():
    model = _ring_model(8, 75e3, tx_images=1)  # absorbing ends: one family; paths [wrap, element, image]
    cos_psi = element_scattering_cosines(model, np.array(150.0), np.array(0.0), 0.0).reshape(model.wraps, 8, 3)
    assert cos_psi[0, 0, 1] == pytest.approx(1.0)  # from the element in line, on to the receiver in line
    assert np.all(np.abs(cos_psi) <= 1.0 + 1e-12)
    assert np.all(cos_psi[0, 1:, 1] < 1.0)  # any other element's wave meets the point at an angle
    mirrored = element_scattering_cosines(model, np.array(150.0), np.array(-20.0), 0.0)
    assert np.sort(mirrored) == pytest.approx(np.sort(element_scattering_cosines(model, np.array(150.0),
                                                                                 np.array(20.0), 0.0)))
    grid = element_scattering_cosines(model, np.array([[60.0], [300.0]]), np.array([[-30.0, 10.0]]), 45.0)
    assert grid[:, 1, 0] == pytest.approx(element_scattering_cosines(model, np.array(300.0), np.array(-30.0), 45.0))


def test_echoes_lagging_forward_are_fitted_with_their_lag_and_not_without_it():
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    n, at = 5000, [(180.0, 50.0)]
    assert np.array_equal(group_waves(scene, at, n, [0.0]), group_waves(scene, at, n))
    waves = group_waves(scene, at, n, [2.0])[:, 0]
    record = np.einsum("mgsn,gs->mn", waves, np.random.default_rng(5).standard_normal(waves.shape[1:3]))
    energy = float(np.sum(record**2))
    with_lag = fit_smooth_echoes(record, scene, at, lags_rad=[2.0])[0]
    assert float(np.sum((record - with_lag) ** 2)) < 1e-12 * energy
    without = fit_smooth_echoes(record, scene, at)[0]
    assert float(np.sum((record - without) ** 2)) > 1e-3 * energy
    with pytest.raises(ValueError, match="Tx elements"):
        fit_smooth_echoes(record, dataclasses.replace(scene, model=PathModel(400.0, MID_WALL_MM, 40.0)), at,
                          lags_rad=[1.0])


def test_echoes_weighted_backward_are_fitted_with_their_weight_and_not_without_it():
    # A thinning of the wall scatters, to first order, in proportion to 1 - cos psi: nothing straight on.
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    n, at = 5000, [(180.0, 50.0)]
    assert np.array_equal(group_waves(scene, at, n, backward=[False]), group_waves(scene, at, n))
    weighted = group_waves(scene, at, n, backward=[True])
    assert float(np.sum(weighted**2)) < float(np.sum(group_waves(scene, at, n) ** 2))  # each path weighs <= 1
    waves = weighted[:, 0]
    record = np.einsum("mgsn,gs->mn", waves, np.random.default_rng(5).standard_normal(waves.shape[1:3]))
    energy = float(np.sum(record**2))
    assert float(np.sum((record - fit_smooth_echoes(record, scene, at, backward=[True])[0]) ** 2)) < 1e-12 * energy
    assert float(np.sum((record - fit_smooth_echoes(record, scene, at)[0]) ** 2)) > 1e-3 * energy
    two = [(180.0, 50.0), (300.0, 230.0)]  # per position: the second scatterer's echoes stay the point's
    both = group_waves(scene, two, n, backward=[True, False])
    assert np.array_equal(both[:, 0], weighted[:, 0]) and np.array_equal(both[:, 1], group_waves(scene, two[1:], n)[:, 0])
    with pytest.raises(ValueError, match="Tx elements"):
        fit_smooth_echoes(record, dataclasses.replace(scene, model=PathModel(400.0, MID_WALL_MM, 40.0)), at,
                          backward=[True])


def test_forward_lags_and_the_backward_weight_are_tried_on_a_sparse_rings_element_model_only_extents_on_any():
    assert multidefect.forward_lags(_ring_model(8, 75e3)) == multidefect.FORWARD_LAGS_RAD
    assert len(multidefect.FORWARD_LAGS_RAD) > 1 and 0.0 in multidefect.FORWARD_LAGS_RAD
    assert multidefect.forward_lags(PathModel(400.0, MID_WALL_MM, 40.0)) == (0.0,)  # a plane wave: it trades with z
    shapes = multidefect.echo_shapes(_ring_model(8, 75e3))
    assert shapes[0] == multidefect.PLAIN and multidefect.EchoShape(backward=True) in shapes
    lines = tuple(multidefect.EchoShape(extent_mm=e) for e in multidefect.EXTENTS_MM)
    assert lines and set(lines) <= set(shapes)
    assert multidefect.echo_shapes(PathModel(400.0, MID_WALL_MM, 40.0)) == (multidefect.PLAIN,) + lines


@pytest.mark.parametrize(("lagged_left", "lag_kept"), [(0.8, 1.0), (0.95, 0.0)])
def test_a_lag_is_kept_only_where_the_echoes_fit_it_decisively_better_than_none(lagged_left, lag_kept):
    # What the echo fit leaves along the line: least at 180 mm with no lag (1.0), at 170 mm with lag 1
    # (``lagged_left``); a lag must leave less than none by more than ECHO_RIVAL_MARGIN (10 %).
    def unexplained_by(at: multidefect.Found, orders: int) -> float:
        z, lag = at.estimate.axial_mm, at.shape.lag_rad
        best_z, least = (180.0, 1.0) if lag == 0.0 and not at.shape.backward else (170.0, lagged_left)
        return least + ((z - best_z) / 20.0) ** 2 + (0.0 if lag in (0.0, 1.0) and not at.shape.backward else 5.0)

    item = multidefect.Found(Estimate(176.0, 50.0, 0.1), None, 0.0)  # type: ignore[arg-type]
    line = multidefect._line_fit(item, item.estimate, 40.0, 2.0, 398.0, unexplained_by,
                                 multidefect.echo_shapes(_ring_model(8, 75e3)))
    assert line is not None and line.shape == multidefect.EchoShape(lag_kept)
    assert line.axial_mm == pytest.approx(170.0 if lag_kept else 180.0, abs=1.0)


@pytest.mark.parametrize(("lag_rad", "backward"), [(0.0, False), (2.0, False), (0.0, True)])
def test_a_sparse_rings_defect_is_placed_along_its_line_with_the_echo_shape_its_echoes_have(monkeypatch, lag_rad,
                                                                                           backward):
    # Echoes of a scatterer at 180 mm 50 deg lagging by lag (1 - cos psi), as a notch's do (lag 2), weighted
    # by (1 - cos psi) / 2, as a thinning's are (backward), or a plain point's (a near-rigid mass); the map put
    # it 14 mm further on. The region round the map's peak is stubbed: the map itself is not what is tested.
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    waves = group_waves(scene, [(180.0, 50.0)], 5000, [lag_rad], [backward])[:, 0]
    record = np.einsum("mgsn,gs->mn", waves, np.random.default_rng(11).standard_normal(waves.shape[1:3]))
    monkeypatch.setattr(multidefect, "peak_confidence", lambda *args, **kwargs: None)
    monkeypatch.setattr(multidefect, "localization_region", lambda *args, **kwargs: Region(30.0, 6.0))
    unexplained = multidefect._unexplained_by(multidefect._Search(record, scene), [])
    item = multidefect.Found(Estimate(194.0, 50.0, 0.1), _bumps(scene.grid, [(194.0, 50.0, 1.0)]), 0.0)
    along = multidefect._echo_fit_angle(multidefect._echo_fit_axial(scene, item, unexplained), unexplained, scene.n_rx)
    placed = multidefect._echo_fit_shape(scene, along, unexplained)  # last, once its line and angle are fixed
    assert placed.estimate.axial_mm == pytest.approx(180.0, abs=1.0)
    assert placed.estimate.angle_deg == pytest.approx(50.0, abs=1.0)
    assert placed.shape == multidefect.EchoShape(lag_rad, backward) and placed.map_peak == item.estimate
    off = dataclasses.replace(placed, estimate=dataclasses.replace(placed.estimate, angle_deg=62.0))
    turned = multidefect._echo_fit_angle(off, unexplained, scene.n_rx)  # turned back with the shape it was placed with
    assert turned.estimate.angle_deg == pytest.approx(50.0, abs=1.0)
    assert turned.shape == multidefect.EchoShape(lag_rad, backward)


def _bumps(grid: Grid, peaks: list[tuple[float, float, float]]) -> DIMap:
    """A DI map on ``grid`` with a narrow bump of the given height at each (axial mm, angle deg, height)."""
    dz = grid.axial_mm[:, None, None] - np.array([p[0] for p in peaks])
    da = np.mod(grid.angle_deg[None, :, None] - np.array([p[1] for p in peaks]) + 180.0, 360.0) - 180.0
    heights = np.array([p[2] for p in peaks])
    return DIMap(np.sum(heights * np.exp(-0.5 * ((dz / 4.0) ** 2 + (da / 2.0) ** 2)), axis=-1), grid, "multipath", 1)


def test_the_maps_other_maxima_within_the_echo_fits_reach_are_further_lines_to_place_a_defect_along():
    # A wavelength is 41.7 mm here (3130 m/s, 75 kHz): the reach is 83 mm along the axis, 22.5 deg round
    # the pipe (half the pitch); a start lies half a wavelength (21 mm) from the peak at least.
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    di_map = _bumps(scene.grid, [(200.0, 45.0, 1.0),
                                 (152.0, 52.5, 0.9), (260.0, 37.5, 0.86),  # starts, highest first
                                 (100.0, 45.0, 0.95),  # beyond the reach along the axis
                                 (200.0, 75.0, 0.95),  # beyond half a pitch
                                 (212.0, 45.0, 0.95),  # the peak's own flank
                                 (240.0, 60.0, 0.8)])  # too low
    starts = multidefect._echo_starts(scene, multidefect.Found(Estimate(200.0, 45.0, 0.1), di_map, 0.0))
    assert [(s.axial_mm, s.angle_deg) for s in starts] == [(152.0, 52.5), (260.0, 37.5)]
    assert all(s.di == 0.1 for s in starts)  # the map's DI stays the defect's


@pytest.mark.parametrize("second_maximum", [True, False])
def test_a_sparse_rings_defect_is_placed_along_the_maps_other_maximum_where_its_echoes_fit_better(
        monkeypatch, second_maximum):
    # Echoes of a scatterer at 180 mm 50 deg; the map's peak lies 52 mm further on and 9 deg round, beyond
    # the reach of the search along its own line (its region, stubbed: +-30 mm). A second maximum of the
    # map at 0.9 of the peak near the scatterer is a further line: along it the echoes fit, and the
    # defect is placed there; without it the defect stays on the peak's line.
    scene = _scene(_ring_model(8, 75e3, tx_images=1), Grid(0.0, 4.0, 101, 0.0, 3.75, 96))
    waves = group_waves(scene, [(180.0, 50.0)], 5000)[:, 0]
    record = np.einsum("mgsn,gs->mn", waves, np.random.default_rng(13).standard_normal(waves.shape[1:3]))
    monkeypatch.setattr(multidefect, "peak_confidence", lambda *args, **kwargs: None)
    monkeypatch.setattr(multidefect, "localization_region", lambda *args, **kwargs: Region(30.0, 6.0))
    unexplained = multidefect._unexplained_by(multidefect._Search(record, scene), [])
    peaks = [(232.0, 41.25, 1.0)] + ([(184.0, 48.75, 0.9)] if second_maximum else [])
    item = multidefect.Found(Estimate(232.0, 41.25, 0.1), _bumps(scene.grid, peaks), 0.0)
    placed = multidefect._echo_fit_axial(scene, item, unexplained)
    assert placed.map_peak == item.estimate and placed.estimate.di == 0.1
    if second_maximum:
        assert placed.estimate.angle_deg == 48.75
        assert placed.estimate.axial_mm == pytest.approx(180.0, abs=2.0)
    else:
        assert placed.estimate.angle_deg == 41.25
        assert placed.estimate.axial_mm >= 232.0 - 30.0


@pytest.mark.parametrize(("axial_mm", "angle_deg"), [(100.0, 45.0), (200.0, 200.0)])
def test_a_near_rigid_mass_seen_by_an_eight_ring_is_found_on_full_wave_physics(axial_mm, angle_deg):
    # The project's own FDTD (fullwave/), not the ray model the imaging was written beside: 8 patches at
    # 75 kHz, absorbing ends, a 10 kg mass on 6 mm. A plane-wave incident model puts the peak 100-200 mm off.
    spec = SimulationSpec(pipe=PipeModel(length_mm=600.0, ends="absorbing"),
                          rings=RingLayout(tx_axial_mm=150.0, n_transducers=8, tx_rx_distance_mm=300.0),
                          excitation_hz=75e3, cell_mm=2.0, n_samples=4000)
    baseline = simulate(spec)
    current = simulate(spec.with_changes(defects=(Mass(axial_mm=axial_mm, angle_deg=angle_deg),)))
    grid = default_grid("multipath", 300.0, baseline.rx_angles_deg)
    result = analyze(baseline, current, wall_mm=4.0)
    assert result.defects, "the mass must be detected"
    best = result.defects[0]
    assert surface_distance_mm(best.axial_mm, best.angle_deg, axial_mm, angle_deg, MID_WALL_MM) < 10.0
    # Its angle rests on the 8 receivers' direct paths alone: the region holds what it may have leant across.
    lean = receiver_lean_mm(best.angle_deg, baseline.rx_angles_deg, current.circumference_mm)
    assert best.region.circumferential_half_mm >= lean > CIRC_FLOOR_MM
    assert best.region.contains(best.axial_mm, best.angle_deg, axial_mm, angle_deg, current.circumference_mm)
    # The plane-wave map with its groups' powers added (measured 181 and 189 mm off); projected on
    # jointly it found the mass at 200 mm 4.7 mm off, the one at 100 mm still 132 mm off.
    plane_scene = Scene.of(baseline, path_model_for(baseline, wall_mm=4.0, elements=False), grid,
                           reference_amplitude_v=reference_amplitude(baseline), joint_groups=False)
    residual = baseline.traces.astype(np.float64) - current.traces.astype(np.float64)
    plane = multipath_pixels(residual_feature(residual, plane_scene), plane_scene)
    i, j = np.unravel_index(np.argmax(plane), plane.shape)
    assert surface_distance_mm(grid.axial_mm[i], grid.angle_deg[j], axial_mm, angle_deg, MID_WALL_MM) > 50.0


def test_a_notch_seen_by_an_eight_ring_without_end_echoes_is_placed_with_its_backward_weight():
    # The project's own FDTD, 8 patches at 75 kHz, absorbing ends, the paper's 20 x 10 x 2 mm notch at 100 mm
    # 45 deg: placed as a plain point, jointly with a second report the search makes 34 mm from the Tx ring
    # round the other side (DI 0.071 against 0.123, before and after), its echoes put it 13.9 mm nearer the
    # Tx ring (measured; alone, at max_defects=1, 1.0 mm); weighted by (1 - cos psi) / 2, as a thinning
    # scatters, they leave decisively less, and place it within 1 mm.
    spec = _small_eight_ring("absorbing")
    result = analyze(simulate(spec), simulate(spec.with_changes(defects=(Notch(axial_mm=100.0, angle_deg=45.0),))),
                     wall_mm=4.0)
    assert result.defects, "the notch must be detected"
    best = result.defects[0]
    assert surface_distance_mm(best.axial_mm, best.angle_deg, 100.0, 45.0, MID_WALL_MM) < 5.0


def _small_eight_ring(ends: str) -> SimulationSpec:
    return SimulationSpec(pipe=PipeModel(length_mm=600.0, ends=ends),  # type: ignore[arg-type]
                          rings=RingLayout(tx_axial_mm=150.0, n_transducers=8, tx_rx_distance_mm=300.0),
                          excitation_hz=75e3, cell_mm=2.0, n_samples=4000)


@pytest.mark.parametrize("ends", ["absorbing", "reflecting"])
def test_a_sparse_rings_wrap_length_and_end_echoes_are_fitted_to_its_baseline(ends):
    # The record says pi x OD = 360 mm; the FDTD's wave travels the mid-wall, 347.5 mm. Order 8's cut-off
    # hangs on it, and order 8's slow arrival lands on the end echoes' window.
    baseline = simulate(_small_eight_ring(ends))
    assert baseline.circumference_mm == pytest.approx(360.03, abs=0.01) and baseline.wall_mm is None
    model = path_model_for(baseline)
    assert model.circumference_mm == pytest.approx(MID_WALL_MM, abs=1.0)
    if ends == "absorbing":
        assert model.near_reflection <= 0.2 and model.far_reflection <= 0.2
        assert receiver_lean(model) == RECEIVER_LEAN  # its defects' angle rests on the direct paths alone
        assert end_reflection_coefficients(baseline)[0] > 0.3  # what the envelope at the echo time reads
        no_ends = path_model_for(dataclasses.replace(baseline, pipe_length_mm=None))  # the direct wave alone
        assert no_ends.near_end_mm is None and no_ends.circumference_mm == pytest.approx(MID_WALL_MM, abs=1.0)
    else:
        assert model.near_reflection >= 0.5 and model.far_reflection >= 0.5
        assert receiver_lean(model) == RECEIVER_LEAN_WITH_ENDS  # the end echoes pin the angle in part
    given = path_model_for(baseline, wall_mm=4.0)  # a wall given: its mid-wall is used, not fitted
    assert given.circumference_mm == pytest.approx(MID_WALL_MM, abs=1e-6)


def test_a_sparse_ring_is_modelled_by_its_elements_only_where_its_baseline_shows_them():
    # The mock node's ray physics launches a plane wave from any ring: no order 8 in its records.
    from mocknode.physics import acquire
    from mocknode.scenario import ExcitationSpec, NodeScenario, RingSpec

    scn = NodeScenario(node_id="eight", rings=RingSpec(n_transducers=8), excitation=ExcitationSpec(frequency_hz=75e3))
    mock = acquire(scn, 0.0, np.random.default_rng(1)).to_measurement(scn)
    assert sparse_ring(8, mock.circumference_mm, mock.velocity_m_s, mock.excitation_hz, mock.cycles)
    model = path_model_for(mock)
    assert not model.elements and model.circumference_mm == mock.circumference_mm  # a plane wave, the record's wrap
    full_wave = simulate(_small_eight_ring("reflecting"))  # the FDTD's 8 patches do launch order 8
    assert path_model_for(full_wave).elements


def test_gather_tables_are_kept_by_bytes_not_by_count(monkeypatch):
    import cachetools

    import imaging.multipath as multipath

    grid = Grid(100.0, 20.0, 4, 0.0, 15.0, 24)
    scene = _scene(_ring_model(8, 75e3, tx_images=1), grid)  # a full ring: one table, rolled, for all receivers
    feature = np.random.default_rng(2).standard_normal((8, 3000)) + 0j
    table_bytes = multipath.build_table(grid, 0.0, scene.model, 3130.0, 0.0, FS_HZ, 3000, 1, 75e3, 5).nbytes
    expected = literal_multipath_pixels(feature, scene)

    def budget(max_bytes: int) -> cachetools.LRUCache:
        cache = cachetools.LRUCache(maxsize=max_bytes, getsizeof=lambda table: table.nbytes)
        monkeypatch.setattr(multipath, "_cached_table", cachetools.cached(cache)(multipath.build_table))
        return cache

    room_for_one = budget(table_bytes)
    np.testing.assert_allclose(multipath_pixels(feature, scene), expected, rtol=1e-4)
    assert room_for_one.currsize == table_bytes and len(room_for_one) == 1
    multipath_pixels(feature, _scene(_ring_model(8, 75e3, tx_images=0), grid))  # another geometry: room is made
    assert len(room_for_one) == 1 and room_for_one.currsize < table_bytes
    too_small = budget(table_bytes // 2)  # a table larger than the whole budget is used, not kept
    np.testing.assert_allclose(multipath_pixels(feature, scene), expected, rtol=1e-4)
    assert len(too_small) == 0
