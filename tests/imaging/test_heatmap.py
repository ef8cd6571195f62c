"""Heatmaps scaled to the node's threshold: the same colour is the same margin on every map, a sound
pipe's noise stays calm, the threshold is on the colour bar, and labels stay readable (issue 16, item 8)."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.colors import rgb_to_hsv
from matplotlib.image import AxesImage

from imaging.dimap import DIMap
from imaging.grid import Grid
from imaging.heatmap import SCALE_MAX_MARGIN, THRESHOLD_COLOUR, heatmap_figure, heatmap_png
from imaging.localize import Estimate

GRID = Grid.default(400.0)
THRESHOLD = 0.026


def _noise_map(peak_di: float, seed: int = 1) -> DIMap:
    pixels = np.abs(np.random.default_rng(seed).normal(0.0, 1.0, GRID.shape))
    return DIMap(pixels * (peak_di / pixels.max()), GRID, "multipath", 0)


def _colours(fig) -> np.ndarray:
    image = next(a for a in fig.axes[0].get_children() if isinstance(a, AxesImage))
    return image.to_rgba(image.get_array())[..., :3]


@pytest.fixture
def figure():
    figures = []

    def make(*args, **kwargs):
        fig = heatmap_figure(*args, **kwargs)
        figures.append(fig)
        return fig

    yield make
    for fig in figures:
        plt.close(fig)


def test_a_sound_pipes_noise_stays_pale_and_grey(figure):
    """DI ~0.003 against a threshold of 0.026: no pixel takes an alarm colour (jet stretched it to red)."""
    rgb = _colours(figure(_noise_map(0.003), threshold=THRESHOLD))
    hsv = rgb_to_hsv(rgb)
    assert hsv[..., 1].max() < 0.12  # no hue anywhere
    assert hsv[..., 2].min() > 0.85  # pale


def test_a_map_above_its_threshold_takes_alarm_colours(figure):
    damaged = _noise_map(0.003).pixels.copy()
    damaged[190:210, 80:100] = 2.5 * THRESHOLD
    hsv = rgb_to_hsv(_colours(figure(DIMap(damaged, GRID, "multipath", 0), threshold=THRESHOLD)))
    assert hsv[90, 200, 2] < 0.5 and hsv[0, 0, 1] < 0.12  # [angle, axial]: the defect dark, the sound wall pale


def test_the_same_margin_is_the_same_colour_on_every_nodes_map(figure):
    quiet = _noise_map(0.02, seed=3)
    loud = DIMap(quiet.pixels * 5.0, GRID, "multipath", 0)  # a node whose DI and threshold are 5x larger
    assert np.array_equal(_colours(figure(quiet, threshold=THRESHOLD)), _colours(figure(loud, threshold=5 * THRESHOLD)))


def test_the_threshold_is_marked_on_the_colour_bar(figure):
    fig = figure(_noise_map(0.003), threshold=THRESHOLD)
    bar_axes = fig.axes[1]
    lines = [line for line in bar_axes.get_lines() if line.get_color() == THRESHOLD_COLOUR]
    assert lines and lines[0].get_ydata()[0] == pytest.approx(THRESHOLD)
    labels = [t.get_text() for t in bar_axes.get_yticklabels()]
    assert f"{THRESHOLD:.3g} threshold" in labels
    assert bar_axes.get_ylim()[1] == pytest.approx(SCALE_MAX_MARGIN * THRESHOLD)


@pytest.mark.parametrize("axial_mm, angle_deg", [(398, 358), (2, 358), (2, 1), (398, 1), (200, 180), (395, 90)])
def test_a_marker_label_stays_inside_the_map_and_off_the_marker(figure, axial_mm, angle_deg):
    mark = Estimate(axial_mm, angle_deg, 0.1)
    fig = figure(_noise_map(0.003), [mark], threshold=THRESHOLD, label="map peak (below threshold)")
    fig.canvas.draw()
    ax = fig.axes[0]
    label = next(t for t in ax.texts if "map peak" in t.get_text())
    text_box = label.get_window_extent()
    map_box = ax.get_window_extent()
    assert map_box.x0 <= text_box.x0 and text_box.x1 <= map_box.x1, "label clipped at the left or right edge"
    assert map_box.y0 <= text_box.y0 and text_box.y1 <= map_box.y1, "label clipped at the top or bottom edge"
    marker_box = ax.get_lines()[0].get_window_extent()
    assert not text_box.overlaps(marker_box), "label over the marker"


def test_one_mark_is_not_numbered_and_the_png_renders(figure):
    fig = figure(_noise_map(0.003), [Estimate(100, 45, 0.003)], threshold=THRESHOLD, label="map peak (below threshold)")
    assert [t.get_text() for t in fig.axes[0].texts] == ["map peak (below threshold)\n100 mm, 45\u00b0"]
    assert heatmap_png(_noise_map(0.003), threshold=THRESHOLD)[:8] == b"\x89PNG\r\n\x1a\n"


def test_without_a_threshold_the_map_uses_its_own_range(figure):
    """The node's own map is in other units (the on-board paper DI): no threshold applies to it."""
    fig = figure(_noise_map(0.5))
    assert fig.axes[1].get_ylim()[1] == pytest.approx(0.5)
