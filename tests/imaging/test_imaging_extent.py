"""A defect's extent round the pipe: a line of points instead of one (imaging/echofit.py ``group_waves``), fitted as
an echo shape where its echoes support it decisively above the record's noise (imaging/multidefect.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from imaging import multidefect
from imaging.echofit import _fit_group_waves, burst_pair, extent_offsets_mm, fit_smooth_echoes, group_waves
from imaging.grid import Grid
from imaging.localize import Estimate
from imaging.paths import PathModel, scalar_paths, stacked_paths, wrap_offsets_mm
from imaging.region import Region
from imaging.scene import Scene
from imaging.timing import MM_PER_M

MID_WALL_MM = math.pi * (114.6 - 4.0)
FS_HZ = 10e6
VELOCITY_M_S = 3250.0
WAVELENGTH_MM = VELOCITY_M_S * MM_PER_M / 85e3


def _plane_scene(n_rx: int = 16, mask: np.ndarray | None = None) -> Scene:
    """A dense ring's scene without end echoes: the plane-wave model, its direct paths only."""
    model = PathModel(400.0, MID_WALL_MM, WAVELENGTH_MM)
    return Scene(rx_angles_deg=np.arange(n_rx) * 360.0 / n_rx,
                 rx_mask=np.ones(n_rx, bool) if mask is None else mask, velocity_m_s=VELOCITY_M_S, t0_s=0.0,
                 fs_hz=FS_HZ, excitation_hz=85e3, cycles=5, window_samples=1, model=model,
                 grid=Grid(0.0, 4.0, 101, 0.0, 2.5, 144))


def test_an_extents_parts_are_the_centres_of_equal_segments_at_most_an_eighth_of_a_wavelength_long():
    assert extent_offsets_mm(0.0, 40.0).tolist() == [0.0]  # no extent: the point itself
    parts = extent_offsets_mm(35.0, 40.0)
    assert parts.size == 7  # 35 mm in segments of at most 5 mm
    np.testing.assert_allclose(parts, (np.arange(7) + 0.5) * 5.0 - 17.5)
    assert extent_offsets_mm(1.0, 40.0).size == 2  # a line has two ends at least


def test_a_part_of_a_line_keeps_its_centres_legs_round_the_pipe_where_its_own_shorter_way_is_the_other():
    # The centre lies 178 deg round from a receiver; a part 6 mm on lies past the receiver's antipode, where its
    # own shorter way round is the other. Its paths follow the centre's legs, each 6 mm longer round the pipe:
    # a group stays a way of leaving the line. Imaged as a point of its own, the two ways swap groups.
    model = PathModel(400.0, MID_WALL_MM, WAVELENGTH_MM, wraps=6)
    z, rel, offset = 200.0, 178.0, 6.0
    _groups, part, _w = stacked_paths(model, np.array(z), np.array(rel), 0.0, offset)
    legs = np.array(wrap_offsets_mm(np.array(rel * MID_WALL_MM / 360.0), MID_WALL_MM, 6))
    np.testing.assert_allclose(part, z + np.hypot(400.0 - z, legs + offset))
    _groups, alone, _w = stacked_paths(model, np.array(z), np.array(rel + offset * 360.0 / MID_WALL_MM))
    np.testing.assert_allclose(np.sort(alone), np.sort(part))  # the same paths ...
    assert not np.allclose(alone, part)  # ... in other groups


def test_a_lines_echoes_are_its_parts_echoes_added_each_with_its_share():
    # Literal oracle: every part as a point of its own (scalar_paths), its bursts weighted 1 / parts. The line
    # (10 mm at 40 deg, 16 receivers) lies clear of every receiver's antipode, where parts would swap groups.
    scene = _plane_scene()
    n, centre_z, centre_deg, extent = 6000, 150.0, 40.0, 10.0
    waves = group_waves(scene, [(centre_z, centre_deg)], n, extents_mm=[extent])[:, 0]  # [m, group, 2, n]
    parts = extent_offsets_mm(extent, scene.wavelength_mm)
    shapes = np.stack(burst_pair(FS_HZ, 85e3, 5))
    literal = np.zeros_like(waves)
    for m, rx_deg in enumerate(scene.rx_angles_deg):
        for offset in parts:
            angle = centre_deg + offset * 360.0 / scene.circumference_mm
            for group, length, weight in scalar_paths(scene.model, centre_z, angle - float(rx_deg)):
                start = math.floor(length / (VELOCITY_M_S * MM_PER_M) * FS_HZ + 0.5)
                stop = min(start + shapes[0].size, n)
                if start < n:
                    literal[m, group, :, start:stop] += weight / parts.size * shapes[:, : stop - start]
    np.testing.assert_allclose(waves, literal, atol=1e-12 * np.abs(literal).max())
    assert np.abs(literal).max() > 0


def _record(scene: Scene, extent_mm: float, noise: float, seed: int) -> np.ndarray:
    """A scatterer at 250 mm 100 deg (``extent_mm`` round the pipe), one random amplitude per path, and white noise
    ``noise`` x the echoes' rms."""
    rng = np.random.default_rng(seed)
    waves = group_waves(scene, [(250.0, 100.0)], 6000, extents_mm=[extent_mm], backward=None)[:, 0]
    echoes = np.einsum("mgsn,gs->mn", waves, rng.standard_normal(waves.shape[1:3]))
    return echoes + noise * np.sqrt(np.mean(echoes ** 2)) * rng.standard_normal(echoes.shape)


def _shape_placed(monkeypatch, record: np.ndarray, with_floor: bool) -> multidefect.Found:
    """The scatterer of ``_record`` placed with its echo shape (``_echo_fit_shape``) from where its map put it, 14 mm
    further on; the region round the map's peak is stubbed (the map is not what is tested)."""
    scene = _plane_scene()
    monkeypatch.setattr(multidefect, "peak_confidence", lambda *args, **kwargs: None)
    monkeypatch.setattr(multidefect, "localization_region", lambda *args, **kwargs: Region(30.0, 6.0))
    search = multidefect._Search(record, scene)
    item = multidefect.Found(Estimate(250.0, 100.0, 0.1), None, 0.0,  # type: ignore[arg-type]
                             map_peak=Estimate(264.0, 100.0, 0.1))
    floor = search.noise_floor() if with_floor else 0.0
    return multidefect._echo_fit_shape(scene, item, multidefect._unexplained_by(search, []), floor)


@pytest.mark.parametrize(("extent_mm", "noise"), [(30.0, 0.0), (30.0, 0.5), (0.0, 0.0)])
def test_a_line_is_placed_with_its_extent_and_a_point_as_a_point(monkeypatch, extent_mm, noise):
    # With noise half the echoes' rms (a fifth of the record) the line still fits decisively better than a point
    # above the noise floor.
    placed = _shape_placed(monkeypatch, _record(_plane_scene(), extent_mm, noise, seed=5), with_floor=True)
    assert placed.shape == multidefect.EchoShape(extent_mm=extent_mm)
    assert placed.estimate.axial_mm == pytest.approx(250.0, abs=2.0)


def test_without_the_noise_floor_a_noisy_lines_extent_is_not_decisive(monkeypatch):
    # The same noisy line judged on what the fits leave of the whole record, noise and all: 10 % of that is more
    # than the line explains beyond a point (0.2 % of the record), so the point is kept (what the floor is for).
    placed = _shape_placed(monkeypatch, _record(_plane_scene(), 30.0, 0.5, seed=5), with_floor=False)
    assert placed.shape == multidefect.PLAIN


def test_the_noise_floor_is_the_noise_before_the_first_arrival_and_every_receiver_not_imaged():
    mask = np.ones(16, bool)
    mask[3] = False
    scene = _plane_scene(mask=mask)
    rng = np.random.default_rng(2)
    noise = 0.01 * rng.standard_normal((16, 6000))
    echoes = _record(scene, 0.0, 0.0, seed=1)  # nothing of them before the direct wave reaches the Rx ring
    first = 400.0 / (VELOCITY_M_S * MM_PER_M) * FS_HZ
    assert np.all(echoes[:, : math.floor(first)] == 0.0) and np.any(echoes != 0.0)
    floor = multidefect._Search(echoes + noise, scene).noise_floor()
    expected = float(np.sum(noise[mask] ** 2)) + float(np.sum((echoes + noise)[3] ** 2))
    assert floor == pytest.approx(expected, rel=0.1)
    assert floor < 0.5 * float(np.sum((echoes + noise) ** 2))  # the echoes themselves are not counted


def test_a_shape_is_judged_on_what_it_leaves_above_the_floor():
    # Along the line the plain point leaves 1.0 at best, a 20 mm line 0.95: within 10 % of the whole, but
    # above a floor of 0.8 it leaves 0.15 against 0.2: decisively less.
    def unexplained_by(at: multidefect.Found, orders: int) -> float:
        least = 0.95 if at.shape.extent_mm == 20.0 else 1.0 if at.shape == multidefect.PLAIN else 2.0
        return least + ((at.estimate.axial_mm - 180.0) / 20.0) ** 2

    item = multidefect.Found(Estimate(176.0, 50.0, 0.1), None, 0.0)  # type: ignore[arg-type]
    shapes = multidefect.echo_shapes(_plane_scene().model)
    judged = {floor: multidefect._line_fit(item, item.estimate, 40.0, 2.0, 398.0, unexplained_by, shapes, floor)
              for floor in (0.0, 0.8)}
    assert judged[0.0] is not None and judged[0.0].shape == multidefect.PLAIN
    assert judged[0.8] is not None and judged[0.8].shape == multidefect.EchoShape(extent_mm=20.0)


@pytest.mark.parametrize("orders", [0, 1, 2])
def test_a_plane_wave_lines_fit_from_its_parts_gram_blocks_equals_the_fit_on_its_whole_columns(orders):
    # Two routes to one fit: the parts as points of their own in the Gram matrix, their blocks added into the
    # line's (fit_smooth_echoes), and every column written out whole as its parts' bursts added (group_waves).
    scene = _plane_scene()
    record = _record(scene, 30.0, 1.0, seed=3)
    at, extents = [(250.0, 100.0), (120.0, 300.0)], [35.0, 0.0]
    parts = fit_smooth_echoes(record, scene, at, orders=orders, extents_mm=extents)
    whole = _fit_group_waves(record, scene, at, orders, shared=True, extents_mm=extents)
    for a, b in zip(parts, whole, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12 * np.abs(record).max())
    assert float(np.sum(parts[0] ** 2)) > 0.1 * float(np.sum(record ** 2))  # the line's echoes are what it fits
