"""DI-map heatmaps as the paper draws them: axial distance on x, angle on y, a colour bar, the estimate marked.

With a threshold, the colour scale is the threshold's, not the map's own range: 0 to
``SCALE_MAX_MARGIN`` x the threshold, the threshold marked on the colour bar. The same colour
then means the same margin on every node's map, and a sound pipe's noise (a DI ~30x below the
threshold) stays pale instead of being stretched over the whole scale: hue-free greys below
the threshold, perceptually uniform reversed magma (orange to black) above it.
"""
from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any, Protocol

import matplotlib

matplotlib.use("Agg")  # headless: no display on gateways or servers
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from imaging.dimap import DIMap

SCALE_MAX_MARGIN = 3.0  # the colour scale ends at 3 x the threshold (an arrow on the bar beyond)
THRESHOLD_COLOUR = "#0b7a75"  # the threshold's mark on the colour bar: a hue the map never uses
_CALM_FROM, _CALM_TO = (0.97, 0.97, 0.97), (0.70, 0.75, 0.80)  # below the threshold: pale greys
_ALARM_FROM = 0.30  # above it: reversed magma from this point (orange) to its end (black)
_ENTRIES = 300


def threshold_colour_map() -> ListedColormap:
    """Pale, hue-free greys below the threshold (the first 1/SCALE_MAX_MARGIN of the scale), then
    reversed magma (perceptually uniform, orange to black) above it. Lightness falls monotonically
    over the whole scale, with a step at the threshold, so the order reads right and an
    exceedance stands out on any card."""
    calm = round(_ENTRIES / SCALE_MAX_MARGIN)
    ramp = np.linspace(0.0, 1.0, calm)[:, None]
    greys = np.hstack([(1 - ramp) * np.array(_CALM_FROM) + ramp * np.array(_CALM_TO), np.ones((calm, 1))])
    alarm = matplotlib.colormaps["magma_r"](np.linspace(_ALARM_FROM, 1.0, _ENTRIES - calm))
    return ListedColormap(np.vstack([greys, alarm]), name="pipesentry_threshold")
LABEL_OFFSET_PT = 12  # label corner from the marker centre: clear of the 14 pt cross
FIGURE_SIZE_IN = (7.0, 4.6)


class MapMark(Protocol):
    """A position to mark on the map (an Estimate, a Defect)."""

    @property
    def axial_mm(self) -> float: ...
    @property
    def angle_deg(self) -> float: ...


def heatmap_figure(
    di_map: DIMap,
    estimates: Sequence[MapMark] = (),
    *,
    threshold: float | None = None,
    threshold_label: str = "threshold",
    truth: Sequence[tuple[float, float]] = (),
    title: str | None = None,
    label: str = "estimate",
    dpi: int = 100,
) -> Figure:
    """The map as a matplotlib figure (the caller closes it). With ``threshold`` the colours are
    scaled to it; without, to the map's own range (a map whose DI has no threshold, e.g. a node's)."""
    grid = di_map.grid
    fig, ax = plt.subplots(figsize=FIGURE_SIZE_IN, dpi=dpi)
    half_a, half_t = grid.axial_step_mm / 2, grid.angle_step_deg / 2
    extent = (
        grid.axial_start_mm - half_a,
        grid.axial_start_mm + grid.axial_step_mm * (grid.axial_count - 1) + half_a,
        grid.angle_start_deg - half_t,
        grid.angle_start_deg + grid.angle_step_deg * (grid.angle_count - 1) + half_t,
    )
    pixels = np.asarray(di_map.pixels, dtype=float)
    scaled = threshold is not None and threshold > 0
    vmax = SCALE_MAX_MARGIN * threshold if scaled and threshold is not None else None
    image = ax.imshow(
        pixels.T, origin="lower", aspect="auto", extent=extent, interpolation="nearest",
        cmap=threshold_colour_map() if scaled else "magma_r", vmin=0.0 if scaled else None, vmax=vmax,
    )
    beyond = vmax is not None and bool(np.nanmax(pixels) > vmax)
    bar = fig.colorbar(image, ax=ax, extend="max" if beyond else "neither")
    if scaled and threshold is not None:
        bar.set_label("damage index")
        ticks = [k * threshold for k in range(int(SCALE_MAX_MARGIN) + 1)]
        bar.set_ticks(ticks, labels=[f"{t:.3g}" + (f" {threshold_label}" if k == 1 else "") for k, t in enumerate(ticks)])
        bar.ax.axhline(threshold, color=THRESHOLD_COLOUR, linewidth=3)
        for tick in bar.ax.get_yticklabels()[1:2]:
            tick.set_color(THRESHOLD_COLOUR)
            tick.set_fontweight("bold")
    else:
        bar.set_label("damage index")
    for k, est in enumerate(estimates):
        ax.plot(est.axial_mm, est.angle_deg, "x", color="white", markersize=14, markeredgewidth=3)
        ax.plot(est.axial_mm, est.angle_deg, "x", color="black", markersize=10, markeredgewidth=1.2)
        numbered = f"{label} {k + 1}" if len(estimates) > 1 else label
        _label_inward(ax, extent, est, f"{numbered}\n{est.axial_mm:.0f} mm, {est.angle_deg:.0f}\u00b0")
    for axial_mm, angle_deg in truth:
        ax.plot(axial_mm, angle_deg, "o", markerfacecolor="none", markeredgecolor="#1f9e4a", markersize=14,
                markeredgewidth=2)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("axial distance from Tx ring (mm)")
    ax.set_ylabel("angle (\u00b0)")
    ax.set_title(title or f"DI map ({di_map.method})")
    return fig


def _label_inward(ax, extent: tuple[float, float, float, float], mark: MapMark, text: str) -> None:
    """The label sits off the marker towards the map's centre (beside it from an outer third, above or
    below it from the middle one): never clipped at an edge, never over the cross; a dark box keeps
    it readable on pale and dark pixels alike."""
    third = (mark.axial_mm - extent[0]) / (extent[1] - extent[0]) * 3
    upper = mark.angle_deg > (extent[2] + extent[3]) / 2
    dx, ha = (LABEL_OFFSET_PT, "left") if third < 1 else (-LABEL_OFFSET_PT, "right") if third > 2 else (0, "center")
    ax.annotate(
        text,
        (mark.axial_mm, mark.angle_deg),
        textcoords="offset points",
        xytext=(dx, -LABEL_OFFSET_PT if upper else LABEL_OFFSET_PT),
        ha=ha,
        va="top" if upper else "bottom",
        color="white",
        fontsize=9,
        fontweight="bold",
        bbox={"boxstyle": "round,pad=0.25", "facecolor": "#1d2330", "edgecolor": "none", "alpha": 0.8},
    )


def heatmap_png(di_map: DIMap, estimates: Sequence[MapMark] = (), **options: Any) -> bytes:
    """Render :func:`heatmap_figure` to PNG bytes."""
    fig = heatmap_figure(di_map, estimates, **options)
    try:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", bbox_inches="tight")
        return buf.getvalue()
    finally:
        plt.close(fig)
