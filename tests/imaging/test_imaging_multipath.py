"""The all-paths map: the fast gather equals the literal per-pixel sum, and it localizes through noise."""
import dataclasses

import cachetools
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imaging import gather, multipath
from imaging.analysis import analyze
from imaging.arrivals import analytic_noise_covariance
from imaging.grid import Grid
from imaging.multipath import literal_multipath_pixels, multipath_pixels
from imaging.paths import PathModel, PathModelError, coherence_groups, wrap_offsets_mm
from imaging.pipeline import AssessSettings, assess
from imaging.scene import Scene
from imaging.timing import surface_distance_mm
from tests.support.synthetic import CIRCUMFERENCE_MM, baseline_and_scatterers


@st.composite
def random_problem(draw):
    n_rx = draw(st.integers(1, 5))
    n_samples = draw(st.integers(20, 600))
    d = draw(st.floats(50, 600))
    with_ends = draw(st.booleans())
    model = PathModel(
        tx_rx_distance_mm=d,
        circumference_mm=draw(st.floats(50, 800)),
        wavelength_mm=draw(st.floats(5, 80)),
        near_end_mm=-draw(st.floats(0, 400)) if with_ends else None,
        far_end_mm=d + draw(st.floats(0, 400)) if with_ends else None,
        near_reflection=draw(st.floats(0, 1)),
        far_reflection=draw(st.floats(0, 1)),
        polarization=draw(st.booleans()),
        wraps=draw(st.sampled_from([1, 2, 3, 6])),  # the map's 2; the echo fit's more
    )
    if draw(st.booleans()):  # a Tx ring modelled element by element (several paths per group and receiver)
        arcs = draw(st.lists(st.floats(0, model.circumference_mm), min_size=1, max_size=3))
        model = dataclasses.replace(model, tx_arcs_mm=tuple(arcs), tx_images=draw(st.integers(0, 1)))
    uniform = draw(st.booleans())
    if uniform:  # a full ring on the grid: exercises the shared, rolled table
        step = draw(st.sampled_from([10.0, 15.0, 30.0]))
        grid = Grid(draw(st.floats(-20, 50)), draw(st.floats(1, 40)), draw(st.integers(1, 8)), 0.0, step, int(360 / step))
        rx = np.arange(n_rx) * step * draw(st.integers(1, 3)) % 360.0
    else:
        grid = Grid(draw(st.floats(-20, 50)), draw(st.floats(1, 40)), draw(st.integers(1, 8)),
                    draw(st.floats(0, 359)), draw(st.floats(1, 40)), draw(st.integers(1, 8)))
        rx = np.array(draw(st.lists(st.floats(0, 359.9), min_size=n_rx, max_size=n_rx)))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    feature = rng.standard_normal((n_rx, n_samples))
    if draw(st.booleans()):
        feature = feature + 1j * rng.standard_normal((n_rx, n_samples))
    mask = rng.random(n_rx) > 0.3
    timing = dict(velocity_m_s=draw(st.floats(1000, 6000)), t0_s=draw(st.floats(-1e-4, 1e-4)),
                  fs_hz=draw(st.floats(2e5, 5e6)))
    scene = Scene(rx_angles_deg=rx, rx_mask=mask, excitation_hz=85e3, cycles=5, window_samples=1, model=model,
                  grid=grid, power=draw(st.sampled_from([1, 2])), joint_groups=draw(st.booleans()), **timing)
    return feature, scene, draw(st.sampled_from(["snr", "amplitude"]))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_problem())
def test_fast_multipath_map_matches_the_literal_sum(problem):
    feature, scene, normalise = problem
    assert_equals_the_literal_map(multipath_pixels(feature, scene, normalise=normalise), feature, scene, normalise)


@pytest.mark.parametrize("joint", [False, True])
def test_a_pixel_a_hair_off_the_receiver_ring_keeps_its_map_value(joint):
    # Found by the test above: a pixel at 49.99999999999999 mm with the receiver ring at 50 gives a
    # polarised path (weight |dz| / r) almost along the ring, w^2 ~ 1e-28 with power 2. The SNR map is
    # the same there as next to it (the weight cancels), but its square in single precision underflowed
    # and the map read 0.
    scene = Scene(rx_angles_deg=np.array([1.0]), rx_mask=np.array([True]), velocity_m_s=1000.0, t0_s=0.0,
                  fs_hz=200000.0, excitation_hz=85e3, cycles=5, window_samples=1,
                  model=PathModel(tx_rx_distance_mm=50.0, circumference_mm=50.0, wavelength_mm=5.0, polarization=True,
                                  wraps=1),
                  grid=Grid(40.99999999999999, 3.0, 4, 0.0, 1.0, 1), power=2, joint_groups=joint)
    assert 0 < abs(scene.grid.axial_mm[-1] - 50.0) < 1e-13
    rng = np.random.default_rng(5)
    feature = rng.standard_normal((1, 20)) + 1j * rng.standard_normal((1, 20))
    fast = multipath_pixels(feature, scene)
    assert fast[-1, 0] > 0.5 * fast[0, 0] > 0
    assert_equals_the_literal_map(fast, feature, scene, "snr")


def assert_equals_the_literal_map(fast: np.ndarray, feature: np.ndarray, scene: Scene, normalise: str) -> None:
    """``fast`` equals the literal map within single precision. The gather sums in float32: its error scales
    with the terms summed, not with what is left after they cancel (a one-pixel map at 1e-4 of its terms was
    8e-5 off relatively); the map of the feature's magnitudes, every term in phase, bounds them."""
    literal = literal_multipath_pixels(feature, scene, normalise=normalise)
    in_phase = literal_multipath_pixels(np.abs(feature).astype(feature.dtype), scene, normalise=normalise)
    scale = max(float(np.abs(literal).max()), float(np.abs(in_phase).max()), 1e-12)
    np.testing.assert_allclose(fast, literal, rtol=0, atol=2e-5 * scale)


def _joint_problem(mask: np.ndarray) -> tuple[np.ndarray, Scene]:
    """A six-receiver ring on a 7 x 36 grid round the pipe, end echoes (several coherence groups), the
    groups projected jointly; a complex feature of noise."""
    model = PathModel(tx_rx_distance_mm=400.0, circumference_mm=340.0, wavelength_mm=38.0, near_end_mm=-300.0,
                      far_end_mm=700.0, near_reflection=0.8, far_reflection=0.6)
    rng = np.random.default_rng(4)
    feature = rng.standard_normal((6, 900)) + 1j * rng.standard_normal((6, 900))
    return feature, Scene(rx_angles_deg=np.arange(6) * 60.0, rx_mask=mask, excitation_hz=85e3, cycles=5,
                          window_samples=1, model=model, grid=Grid(30.0, 45.0, 7, 0.0, 10.0, 36), power=1,
                          joint_groups=True, velocity_m_s=3250.0, t0_s=0.0, fs_hz=1e6)


def test_a_grids_gram_whitenings_are_kept_by_bytes_not_by_count(monkeypatch):
    # A receiver mask that changes (a channel that comes and goes) makes another whitening: what is kept
    # is bounded by bytes, and one larger than the whole budget is used, not kept.
    feature, scene = _joint_problem(np.ones(6, bool))
    _, other = _joint_problem(np.arange(6) != 2)
    expected = literal_multipath_pixels(feature, scene)

    kept = multipath._gram_whitening_total.cache
    multipath._gram_whitening_total.cache_clear()
    multipath_pixels(feature, scene)
    whitening_bytes = kept.currsize
    groups = coherence_groups(scene.model)
    assert len(kept) == 1 and whitening_bytes == 2 * groups * (groups + 1) // 2 * 7 * 36 * 4  # [2, G (G + 1) / 2, pixels]
    assert kept.maxsize == multipath.GRAM_CACHE_BYTES

    def budget(max_bytes: int) -> cachetools.LRUCache:
        cache = cachetools.LRUCache(maxsize=max_bytes, getsizeof=kept.getsizeof)
        monkeypatch.setattr(multipath, "_gram_whitening_total",
                            cachetools.cached(cache)(multipath._gram_whitening_total.__wrapped__))
        return cache

    room_for_one = budget(whitening_bytes)
    np.testing.assert_allclose(multipath_pixels(feature, scene), expected, rtol=0, atol=2e-5 * np.abs(expected).max())
    multipath_pixels(feature, other)  # another mask: room is made
    assert len(room_for_one) == 1 and room_for_one.currsize == whitening_bytes
    too_small = budget(whitening_bytes - 1)
    np.testing.assert_allclose(multipath_pixels(feature, scene), expected, rtol=0, atol=2e-5 * np.abs(expected).max())
    assert len(too_small) == 0


@pytest.mark.parametrize("healthy", [6, 5])  # all six receivers (one table turned six times round), or one off
@pytest.mark.parametrize("block_pixels", [5, 36, 72, 1 << 13])
def test_a_joint_maps_gram_whitening_built_a_few_rings_of_pixels_at_a_time_is_the_literal_sums(monkeypatch,
                                                                                              block_pixels, healthy):
    # A 1 mm x 1 deg map's Grams would be ~0.75 GB at once: they are summed and factored whole rings
    # of pixels at a time (GRAM_BLOCK_PIXELS; fewer pixels than a ring: one ring). Receivers on the
    # grid share a table turned round the pipe, and a turn never crosses a block: 1, 2 (7 rows =
    # 2 + 2 + 2 + 1) or all rows at a time give the literal per-pixel map.
    feature, scene = _joint_problem(np.arange(6) != (2 if healthy < 6 else -1))
    monkeypatch.setattr(multipath, "GRAM_BLOCK_PIXELS", block_pixels)
    multipath._gram_whitening_total.cache_clear()
    try:
        fast = multipath_pixels(feature, scene)
    finally:
        multipath._gram_whitening_total.cache_clear()  # no whitening built with this block size is kept
    literal = literal_multipath_pixels(feature, scene)
    np.testing.assert_allclose(fast, literal, rtol=0, atol=2e-5 * float(np.abs(literal).max()))


@pytest.mark.parametrize("turns", [[0, 9, 18, 27], [5, 14, 23, 32], [32, 5, 23, 14], [0, 12, 24], [0, 9, 18],
                                   [3], [0, 0], [0, 18]])
def test_a_table_shared_by_several_receivers_adds_its_turns_folded_or_one_by_one_alike(turns):
    # Turns in k equal steps round the pipe (the first four: 4 x 9 of 36 pixels, one 3 x 12) are added
    # folded; the others one by one; either way each is np.roll's.
    rng = np.random.default_rng(len(turns))
    part = rng.standard_normal((2, 2, 3, 36)) + 1j * rng.standard_normal((2, 2, 3, 36))
    total = rng.standard_normal(part.shape) + 1j * rng.standard_normal(part.shape)
    expected = total + sum(np.roll(part, turn, axis=-1) for turn in turns)
    multipath._add_turns(total, part, turns)
    np.testing.assert_allclose(total, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("echo_placed", [False, True])
def test_groups_projected_jointly_place_a_point_the_power_sum_pulls_towards_the_rx_ring(echo_placed, monkeypatch):
    # An isotropic point of the map's own model at 80 mm, no end echoes: on the far receivers its
    # two ways round arrive within a burst of each other; adding the groups' powers counts that
    # overlap twice and moves the peak >10 mm towards the Rx ring, the joint projection does not.
    # A defect without end echoes is then placed by its echo fit (imaging/multidefect.py
    # ``echo_placed``), which starts from either map's peak and puts both on the point.
    from imaging import multidefect

    if not echo_placed:  # the maps' peaks themselves
        monkeypatch.setattr(multidefect, "echo_placed", lambda model, di: bool(model.elements))
    base, cur = baseline_and_scatterers([(80.0, 10.0, 0.05)], noise_rms=5e-4, seed=2)
    errors = []
    for joint in (False, True):
        found = assess(cur, [base], AssessSettings(joint_groups=joint)).defects
        assert len(found) == 1
        errors.append(surface_distance_mm(found[0].axial_mm, found[0].angle_deg, 80.0, 10.0, CIRCUMFERENCE_MM))
    assert errors[0] < 3.0 if echo_placed else errors[0] > 10.0
    assert errors[1] < 3.0


def test_a_path_model_follows_the_scattered_wave_round_the_pipe_either_way_turn_by_turn():
    # Legs: the shorter way, the other way, then each once more round the pipe, alternately.
    for arc in (30.0, -30.0):
        way = 1.0 if arc > 0 else -1.0
        legs = [float(x) for x in wrap_offsets_mm(np.array(arc), 360.0, 6)]
        assert legs == [arc, arc - way * 360.0, arc + way * 360.0, arc - way * 720.0, arc + way * 720.0,
                        arc - way * 1080.0]
    assert [float(x) for x in wrap_offsets_mm(np.array(30.0), 360.0, 2)] == [30.0, -330.0]
    with pytest.raises(PathModelError, match="wraps"):
        PathModel(400.0, 360.0, 38.0, wraps=0)


@pytest.mark.parametrize("axial_mm, angle_deg", [(100, 90), (200, 157.5), (300, 315)])
def test_multipath_localizes_a_noisy_scatterer_where_the_paper_method_fails(axial_mm, angle_deg):
    # White noise of 0.2 % of the direct arrival's peak on both records.
    base, cur = baseline_and_scatterers([(axial_mm, angle_deg, 0.05)], noise_rms=0.002, seed=3)
    new = analyze(base, cur).peak
    paper = analyze(base, cur, method="paper").peak
    err_new = surface_distance_mm(new.axial_mm, new.angle_deg, axial_mm, angle_deg, CIRCUMFERENCE_MM)
    err_paper = surface_distance_mm(paper.axial_mm, paper.angle_deg, axial_mm, angle_deg, CIRCUMFERENCE_MM)
    assert err_new < 10.0
    assert err_paper > 2 * err_new


def test_noise_alone_is_not_detected_and_a_scatterer_is():
    quiet_base, quiet_cur = baseline_and_scatterers([], noise_rms=0.002, seed=5)
    base, cur = baseline_and_scatterers([(250.0, 40.0, 0.05)], noise_rms=0.002, seed=5)
    quiet, loud = analyze(quiet_base, quiet_cur), analyze(base, cur)
    assert not quiet.detected and quiet.defects == []
    assert loud.detected and loud.peak_di > 3 * quiet.peak_di
    assert loud.as_json()["detected"] is True and loud.as_json()["method"] == "multipath"


def _ridged(grams: np.ndarray) -> np.ndarray:
    """[pixel, G, G] Grams with multipath.GRAM_RIDGE of their largest diagonal term on the diagonal."""
    largest = np.einsum("xgg->xg", grams).real.max(axis=1)
    return grams + multipath.GRAM_RIDGE * largest[:, None, None] * np.eye(grams.shape[1])


def test_the_whitened_power_holds_in_single_precision_where_the_inverse_gram_would_not():
    # Two groups whose paths nearly coincide make the Gram as ill-conditioned as the ridge lets it be
    # (cond ~2e6). The power is read as |W b|^2 with W = L^-1 held in single precision: a sum of
    # squares, so W's rounding moves it by ~sqrt(cond) x 6e-8. The inverse Gram itself held in single
    # precision (the Hermitian form b^H M^-1 b) moves it by up to cond x 6e-8 of itself.
    rng = np.random.default_rng(3)
    n_groups, n_pix = 6, 200
    columns = rng.standard_normal((n_pix, 40, n_groups)) + 1j * rng.standard_normal((n_pix, 40, n_groups))
    columns[:, :, 1] = columns[:, :, 0] + 1e-4 * columns[:, :, 1]  # groups 0 and 1 all but the same
    grams = np.einsum("xkg,xkh->xgh", columns.conj(), columns)
    sums = rng.standard_normal((n_groups, n_pix)) + 1j * rng.standard_normal((n_groups, n_pix))
    sums[1] = sums[0]  # what both nearly coinciding groups see alike: M^-1's large terms cancel in the form
    exact_inverse = np.linalg.inv(_ridged(grams))
    exact = np.einsum("gx,xgh,hx->x", sums.conj(), exact_inverse, sums).real
    whitened = gather.joint_power(sums, multipath.gram_whitening(np.moveaxis(grams, 0, -1).copy()))
    single_inverse = np.einsum("gx,xgh,hx->x", sums.conj(), exact_inverse.astype(np.complex64).astype(np.complex128),
                               sums).real
    assert float(np.max(np.abs(whitened - exact) / exact)) < 1e-5  # measured 7e-7
    assert float(np.max(np.abs(single_inverse - exact) / exact)) > 1e-3  # measured 0.03


def test_a_gram_rounded_indefinite_is_whitened_with_its_eigenvalues_floored_not_refused():
    # A Gram is a covariance, positive semi-definite; one whose sum rounding left an eigenvalue below
    # minus the ridge has no Cholesky factor: it is whitened as the Gram with that eigenvalue at the
    # ridge, the rest as they are (the inverse it replaced never refused one either).
    grams = np.zeros((2, 2, 2), dtype=np.complex128)
    grams[:, :, 0] = [[2.0, 0.0], [0.0, 1.0]]
    grams[:, :, 1] = [[1.0, 0.0], [0.0, -1e-3]]  # -1e-3 of the largest: far beyond the ridge (1e-6 of it)
    packed = multipath.gram_whitening(grams.copy(), np.float64)
    sums = np.array([[1.0, 1.0], [1.0, 1.0]], dtype=np.complex64)
    floor = multipath.GRAM_RIDGE * 1.0
    np.testing.assert_allclose(gather.joint_power(sums, packed),
                               [1 / (2 + 2e-6) + 1 / (1 + 2e-6), 1 / (1 + floor) + 1 / floor], rtol=1e-9)


def test_a_pixel_no_path_reaches_has_no_power_and_no_overflow():
    # An empty Gram (no group has a path there) would whiten to 1 / sqrt of the ridge's floor,
    # beyond single precision: its whitening is zero instead, and its power 0 (its sums are 0).
    rng = np.random.default_rng(8)
    grams = np.zeros((3, 3, 2), dtype=np.complex128)
    columns = rng.standard_normal((20, 3)) + 1j * rng.standard_normal((20, 3))
    grams[:, :, 1] = columns.conj().T @ columns
    with np.errstate(all="raise"):
        packed = multipath.gram_whitening(grams.copy())
    assert np.all(np.isfinite(packed)) and not np.any(packed[:, :, 0])
    sums = np.zeros((3, 2), dtype=np.complex64)
    sums[:, 1] = [1.0, 2.0j, -1.0]
    power = gather.joint_power(sums, packed)
    exact = np.vdot(sums[:, 1], np.linalg.solve(_ridged(grams[None, :, :, 1])[0], sums[:, 1])).real
    assert power[0] == 0.0 and power[1] == pytest.approx(exact, rel=1e-5)


@pytest.mark.skipif(not gather.compiled(), reason="numba is not installed")
def test_compiled_cross_gram_and_joint_power_equal_their_numpy_sums():
    rng = np.random.default_rng(11)
    covariance = analytic_noise_covariance(10e6, 85e3, 5)
    groups = rng.integers(0, 4, 10).astype(np.int64)
    idx = rng.integers(0, 900, (10, 30)).astype(np.int32)  # 900 = outside a record of 900 samples
    w = rng.random((10, 30)).astype(np.float32)
    fast = gather.cross_gram(groups, idx, w, covariance, 4, 900)
    slow = gather.cross_gram_numpy(groups, idx, w, covariance, 4, 900)
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-12)
    per_pixel = np.moveaxis(fast, 2, 0)
    np.testing.assert_allclose(per_pixel, np.conj(np.swapaxes(per_pixel, 1, 2)), atol=1e-12)  # Hermitian
    assert np.all(np.linalg.eigvalsh(per_pixel) > -1e-9)  # a covariance: positive semi-definite
    sums = rng.standard_normal((4, 30)) + 1j * rng.standard_normal((4, 30))
    ridged = per_pixel + 1e-3 * np.eye(4)
    full = np.einsum("xg,xgh,xh->x", sums.T.conj(), np.linalg.inv(ridged), sums.T).real  # b^H M^-1 b, whole
    packed = gather.pack_lower(np.linalg.inv(np.linalg.cholesky(ridged)))  # W = L^-1: W^H W = M^-1
    assert packed.shape == (2, 10, 30) and packed.dtype == np.float32  # 4 x 5 / 2 complex numbers a pixel
    np.testing.assert_allclose(gather.joint_power(sums, packed), full, rtol=1e-5)  # W held in single precision
    np.testing.assert_allclose(gather.joint_power_numpy(sums, packed), gather.joint_power(sums, packed), rtol=1e-12)
