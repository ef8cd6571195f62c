"""DI-map heatmaps as the paper draws them: axial distance on x, angle on y, a colour bar, the estimate marked."""
from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Protocol

import matplotlib

matplotlib.use("Agg")  # headless: no display on gateways or servers
import matplotlib.pyplot as plt

from imaging.dimap import DIMap


class MapMark(Protocol):
    """A position to mark on the map (an Estimate, a Defect)."""

    @property
    def axial_mm(self) -> float: ...
    @property
    def angle_deg(self) -> float: ...


def heatmap_png(
    di_map: DIMap,
    estimates: Sequence[MapMark] = (),
    *,
    truth: Sequence[tuple[float, float]] = (),
    title: str | None = None,
    label: str = "estimate",
    dpi: int = 100,
) -> bytes:
    """Render the map to PNG bytes; estimates as white crosses named ``label``, true positions as open circles."""
    grid = di_map.grid
    fig, ax = plt.subplots(figsize=(7.0, 4.6), dpi=dpi)
    try:
        half_a, half_t = grid.axial_step_mm / 2, grid.angle_step_deg / 2
        extent = (
            grid.axial_start_mm - half_a,
            grid.axial_start_mm + grid.axial_step_mm * (grid.axial_count - 1) + half_a,
            grid.angle_start_deg - half_t,
            grid.angle_start_deg + grid.angle_step_deg * (grid.angle_count - 1) + half_t,
        )
        image = ax.imshow(
            di_map.pixels.T, origin="lower", aspect="auto", extent=extent, cmap="jet", interpolation="nearest"
        )
        fig.colorbar(image, ax=ax, label="damage index")
        for k, est in enumerate(estimates):
            ax.plot(est.axial_mm, est.angle_deg, "x", color="white", markersize=14, markeredgewidth=3)
            ax.plot(est.axial_mm, est.angle_deg, "x", color="black", markersize=10, markeredgewidth=1.2)
            right_half = est.axial_mm > extent[0] + 0.55 * (extent[1] - extent[0])
            ax.annotate(
                f"{label} {k + 1}: {est.axial_mm:.0f} mm, {est.angle_deg:.0f}\u00b0",
                (est.axial_mm, est.angle_deg),
                textcoords="offset points",
                xytext=(-10, 8) if right_half else (8, 8),
                ha="right" if right_half else "left",
                color="white",
                fontsize=9,
                fontweight="bold",
            )
        for axial_mm, angle_deg in truth:
            ax.plot(axial_mm, angle_deg, "o", markerfacecolor="none", markeredgecolor="magenta", markersize=14)
        ax.set_xlabel("axial distance from Tx ring (mm)")
        ax.set_ylabel("angle (\u00b0)")
        ax.set_title(title or f"DI map ({di_map.method})")
        buf = io.BytesIO()
        fig.savefig(buf, format="png", bbox_inches="tight")
        return buf.getvalue()
    finally:
        plt.close(fig)
