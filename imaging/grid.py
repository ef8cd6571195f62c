"""The pixel grid of a DI map: the unrolled pipe wall, axial position x angle."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class GridError(ValueError):
    """A grid specification is malformed."""


@dataclass(frozen=True)
class Grid:
    """Pixel centres: ``axial_mm`` measured from the Tx ring, ``angle_deg`` on the circumference.

    Both axes are uniform (start, step, count), which is what the node protocol and the
    database store; ``spec()``/``from_spec()`` convert to and from that form.
    """

    axial_start_mm: float
    axial_step_mm: float
    axial_count: int
    angle_start_deg: float
    angle_step_deg: float
    angle_count: int

    def __post_init__(self) -> None:
        if self.axial_count < 1 or self.angle_count < 1:
            raise GridError("a grid needs at least one pixel on each axis")
        if not (self.axial_step_mm > 0 and self.angle_step_deg > 0):
            raise GridError("grid steps must be positive")
        if self.angle_step_deg * self.angle_count > 360.0 + 1e-9:
            raise GridError("the angle axis must not cover more than one turn")

    @classmethod
    def default(cls, tx_rx_distance_mm: float, axial_step_mm: float = 1.0, angle_step_deg: float = 1.0) -> Grid:
        """1 mm x 1 deg over 0..tx_rx_distance (inclusive) x 0..359 deg, as in the paper's figures."""
        axial_count = int(np.floor(tx_rx_distance_mm / axial_step_mm + 1e-9)) + 1
        angle_count = round(360.0 / angle_step_deg)
        return cls(0.0, float(axial_step_mm), axial_count, 0.0, float(angle_step_deg), angle_count)

    @property
    def axial_mm(self) -> np.ndarray:
        return self.axial_start_mm + self.axial_step_mm * np.arange(self.axial_count, dtype=np.float64)

    @property
    def angle_deg(self) -> np.ndarray:
        return np.mod(self.angle_start_deg + self.angle_step_deg * np.arange(self.angle_count, dtype=np.float64), 360.0)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.axial_count, self.angle_count)

    @property
    def wraps_in_angle(self) -> bool:
        """True when the angle axis covers the whole circumference (neighbours wrap round)."""
        return abs(self.angle_step_deg * self.angle_count - 360.0) < 1e-9

    def spec(self) -> dict:
        return {
            "axial_start_mm": self.axial_start_mm,
            "axial_step_mm": self.axial_step_mm,
            "axial_count": self.axial_count,
            "angle_start_deg": self.angle_start_deg,
            "angle_step_deg": self.angle_step_deg,
            "angle_count": self.angle_count,
        }

    @classmethod
    def from_spec(cls, spec: dict) -> Grid:
        try:
            return cls(
                float(spec["axial_start_mm"]),
                float(spec["axial_step_mm"]),
                int(spec["axial_count"]),
                float(spec["angle_start_deg"]),
                float(spec["angle_step_deg"]),
                int(spec["angle_count"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise GridError(f"bad grid spec: {exc}") from exc
