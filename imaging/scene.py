"""What a record and its baseline share, resolved once: the value passed along the imaging route.

    assess -> select baseline -> Scene -> feature -> map -> peaks -> refine

A ``Scene`` holds everything the all-paths imaging needs besides the residual itself: the
receivers (angles, which are healthy), the timing (velocity, t0, sampling), the excitation
(frequency, cycles, window), the path model, the map grid, the feature and its weight
exponent, the reference amplitude that makes the feature unit-free, and the filter the
residual has been through. ``Scene.of`` reads them off the (matched) baseline; the imaging
functions (imaging/features.py ``residual_feature``, imaging/multipath.py ``multipath_pixels``,
``local_multipath_pixels``, imaging/echofit.py ``fit_echoes``, imaging/multidefect.py
``find_defects``) take the scene instead of a dozen loose parameters, so nothing is
re-derived, or derived differently, on the way.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from imaging.dimap import default_window_samples
from imaging.grid import Grid
from imaging.measurement import Measurement
from imaging.paths import PathModel
from imaging.timing import MM_PER_M


class SceneError(ValueError):
    """A scene's parts do not fit together (receiver mask length, amplitude, feature)."""


def feature_power(feature: str) -> int:
    """Weight exponent q: 2 for an energy feature, 1 for amplitude features."""
    return 2 if feature == "squared" else 1


@dataclass(frozen=True, eq=False)
class Scene:
    """The shared, resolved geometry of one record against its baseline (see the module docstring).

    ``rx_mask`` True for the receivers imaged; ``project`` the filter the residual has been
    through (fitted echoes are put through it too), None for none. Arrays are read-only."""

    rx_angles_deg: np.ndarray
    rx_mask: np.ndarray
    velocity_m_s: float
    t0_s: float
    fs_hz: float
    excitation_hz: float
    cycles: int
    window_samples: int
    model: PathModel
    grid: Grid
    feature: str = "analytic"
    power: int = 1
    reference_amplitude_v: float = 1.0
    project: Callable[[np.ndarray], np.ndarray] | None = None
    joint_groups: bool = True  # a coherent map projects on its groups jointly (imaging/multipath.py)

    def __post_init__(self) -> None:
        angles = np.array(self.rx_angles_deg, dtype=np.float64)
        mask = np.ones(angles.size, bool) if self.rx_mask is None else np.array(self.rx_mask, dtype=bool)
        if angles.ndim != 1 or mask.shape != angles.shape:
            raise SceneError(f"rx_mask has {mask.size} entries for {angles.size} receivers")
        if not self.reference_amplitude_v > 0:
            raise SceneError("reference_amplitude_v must be positive")
        angles.setflags(write=False)
        mask.setflags(write=False)
        object.__setattr__(self, "rx_angles_deg", angles)
        object.__setattr__(self, "rx_mask", mask)

    @classmethod
    def of(cls, reference: Measurement, model: PathModel, grid: Grid | None = None, *, feature: str = "analytic",
           reference_amplitude_v: float = 1.0, rx_mask: np.ndarray | None = None,
           project: Callable[[np.ndarray], np.ndarray] | None = None, joint_groups: bool = True) -> Scene:
        """The scene of records taken with ``reference``'s receivers, timing and excitation."""
        return cls(
            rx_angles_deg=reference.rx_angles_deg,
            rx_mask=np.ones(reference.n_rx, bool) if rx_mask is None else rx_mask,
            velocity_m_s=float(reference.velocity_m_s),
            t0_s=float(reference.t0_s),
            fs_hz=float(reference.fs_hz),
            excitation_hz=float(reference.excitation_hz),
            cycles=int(reference.cycles),
            window_samples=default_window_samples(reference),
            model=model,
            grid=grid or Grid.default(reference.tx_rx_distance_mm),
            feature=feature,
            power=feature_power(feature),
            reference_amplitude_v=float(reference_amplitude_v),
            project=project,
            joint_groups=joint_groups,
        )

    @property
    def n_rx(self) -> int:
        return int(self.rx_angles_deg.size)

    @property
    def wavelength_mm(self) -> float:
        """The T(0,1) wavelength at the excitation frequency (the record's wave speed)."""
        return self.velocity_m_s * MM_PER_M / self.excitation_hz

    @property
    def circumference_mm(self) -> float:
        """The wrap length of the scattered waves (the path model's)."""
        return float(self.model.circumference_mm)

    def with_grid(self, grid: Grid) -> Scene:
        """The same scene imaged on another grid (a peak's neighbourhood, one pixel)."""
        return dataclasses.replace(self, grid=grid)

    def with_feature(self, feature: str) -> Scene:
        return dataclasses.replace(self, feature=feature, power=feature_power(feature))


__all__ = ["Scene", "SceneError", "feature_power"]
