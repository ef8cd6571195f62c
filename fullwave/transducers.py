"""The rings of shear transducers: what the Tx ring drives and what the Rx ring senses.

Every Tx transducer is a finite patch (15 x 15 mm by default) pressing a uniform surface
traction on the wall; they all fire together with the same Hann-windowed tone burst (one record
is one simulation). The traction points round the circumference, optionally tilted towards the
axis by ``tilt_deg`` (a misaligned or cross-coupled shear patch), which in the in-plane model
launches the S0-like longitudinal wave as well. A receiver's output is the wall's particle
velocity along the same direction, averaged over its patch: for a T(0,1) wave travelling one
way that is, up to the factor -1/c, the shear strain a bonded shear patch senses.
Uniform traction ignores the shear lag that concentrates a bonded patch's load at its edges.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fullwave.grid import Grid, rectangle_coverage

MM = 1e-3


class TransducerError(ValueError):
    """A ring that does not fit the pipe or the grid."""


def tone_burst(t_s: np.ndarray, frequency_hz: float, cycles: int) -> np.ndarray:
    """H(t) = 0.5 (1 - cos(2 pi f t / n)) sin(2 pi f t) for 0 <= t <= n / f, else 0 (paper, eq. 1)."""
    t = np.asarray(t_s, dtype=np.float64)
    phase = 2 * math.pi * frequency_hz * t
    return np.where((t >= 0) & (t <= cycles / frequency_hz), 0.5 * (1 - np.cos(phase / cycles)) * np.sin(phase), 0.0)


def equal_angles(n: int) -> tuple[float, ...]:
    return tuple(360.0 * k / n for k in range(n))


@dataclass(frozen=True)
class RingLayout:
    """Tx ring at ``tx_axial_mm`` from the pipe end behind it, the Rx ring ``tx_rx_distance_mm`` further."""

    tx_axial_mm: float = 300.0
    tx_rx_distance_mm: float = 400.0
    n_transducers: int = 16
    patch_circumferential_mm: float = 15.0
    patch_axial_mm: float = 15.0
    tilt_deg: float = 0.0
    tx_angles_deg: tuple[float, ...] | None = None
    rx_angles_deg: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.n_transducers < 1:
            raise TransducerError("a ring needs at least one transducer")
        for name in ("tx_angles_deg", "rx_angles_deg"):
            angles = getattr(self, name)
            if angles is not None and len(angles) != self.n_transducers:
                raise TransducerError(f"{name} lists {len(angles)} angles for {self.n_transducers} transducers")
        if not (self.patch_circumferential_mm > 0 and self.patch_axial_mm > 0):
            raise TransducerError("transducer patches need a positive size")
        if not -90.0 < self.tilt_deg < 90.0:
            raise TransducerError("tilt_deg must lie strictly between -90 and 90 degrees")

    @property
    def tx_angles(self) -> tuple[float, ...]:
        return self.tx_angles_deg if self.tx_angles_deg is not None else equal_angles(self.n_transducers)

    @property
    def rx_angles(self) -> tuple[float, ...]:
        return self.rx_angles_deg if self.rx_angles_deg is not None else equal_angles(self.n_transducers)

    @property
    def rx_axial_mm(self) -> float:
        return self.tx_axial_mm + self.tx_rx_distance_mm

    @property
    def direction(self) -> tuple[float, float]:
        """(axial, circumferential) components of the unit traction / sensing direction."""
        tilt = math.radians(self.tilt_deg)
        return math.sin(tilt), math.cos(tilt)


@dataclass(frozen=True)
class PatchWeights:
    """Sparse weights on one staggered grid: flat cell indices and their coverage."""

    index: np.ndarray
    weight: np.ndarray
    owner: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # receiver row

    def by_row(self, nz: int, ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The weights of a [nz, ns] grid row by row: (row pointers [nz + 1], columns, weights), for a
        kernel that adds them while it passes each row."""
        order = np.argsort(self.index, kind="stable")
        index, weight = self.index[order], self.weight[order]
        ptr = np.searchsorted(index // ns, np.arange(nz + 1)).astype(np.int64)
        return ptr, (index % ns).astype(np.int64), weight


def _patch(grid: Grid, axial_mm: float, angle_deg: float, layout: RingLayout, on_faces: bool,
           s_offset: float) -> np.ndarray:
    z_m = axial_mm * MM
    s_m = (angle_deg % 360.0) / 360.0 * grid.circumference_m
    half_z, half_s = layout.patch_axial_mm * MM / 2, layout.patch_circumferential_mm * MM / 2
    if not (half_z <= z_m <= grid.length_m - half_z):
        raise TransducerError(f"a ring at {axial_mm} mm does not fit on the {grid.length_m / MM:g} mm pipe")
    return rectangle_coverage(grid, z_m - half_z, z_m + half_z, s_m - half_s, s_m + half_s, on_faces, s_offset)


def forcing_weights(coverage: np.ndarray) -> PatchWeights:
    """Sparse form of a traction pattern [nz, ns] (traction density = amplitude x coverage)."""
    flat = np.asarray(coverage, dtype=np.float64).ravel()
    index = np.flatnonzero(flat > 0)
    return PatchWeights(index, flat[index])


def averaging_weights(coverages: list[np.ndarray]) -> PatchWeights:
    """Receiver k averages the field over ``coverages[k]`` (its weights sum to 1); ``owner`` is k."""
    index, weight, owner = [], [], []
    for row, coverage in enumerate(coverages):
        flat = np.asarray(coverage, dtype=np.float64).ravel()
        cells = np.flatnonzero(flat > 0)
        if cells.size == 0:
            raise TransducerError(f"receiver {row} covers no cell")
        index.append(cells)
        weight.append(flat[cells] / flat[cells].sum())
        owner.append(np.full(cells.size, row))
    return PatchWeights(np.concatenate(index), np.concatenate(weight), np.concatenate(owner))


def tx_weights(grid: Grid, layout: RingLayout, on_faces: bool = False, s_offset: float = 0.0) -> PatchWeights:
    """All Tx patches together, on the control cells of one staggered grid (grid.rectangle_coverage)."""
    if layout.n_transducers * layout.patch_circumferential_mm > grid.circumference_m / MM + 1e-9:
        raise TransducerError("the Tx patches overlap: n_transducers x width exceeds the circumference")
    total = np.zeros((grid.nz + 1 if on_faces else grid.nz, grid.ns))
    for angle in layout.tx_angles:
        total += _patch(grid, layout.tx_axial_mm, angle, layout, on_faces, s_offset)
    return forcing_weights(total)


def rx_weights(grid: Grid, layout: RingLayout, on_faces: bool = False, s_offset: float = 0.0) -> PatchWeights:
    """Each receiver's patch-averaging weights, in the order of ``layout.rx_angles``."""
    return averaging_weights([_patch(grid, layout.rx_axial_mm, a, layout, on_faces, s_offset)
                              for a in layout.rx_angles])


def plane_wave_velocity_m_s(layout: RingLayout, circumference_m: float, areal_mass_kg_m2: float,
                            velocity_m_s: float, traction_pa: float) -> float:
    """Peak particle velocity of the axisymmetric wave a Tx ring launches each way, far from the ring.

    A line force F per unit circumference (the ring's total force spread round it) splits into two
    waves of velocity F / (2 rho h c) (jump of mu h dw/dz across the ring). The patch's axial
    length l filters the pulse by sinc(f l / c) on top (not included here).
    """
    force_per_m = (layout.n_transducers * layout.patch_axial_mm * layout.patch_circumferential_mm * MM * MM
                   * traction_pa / circumference_m)
    return force_per_m / (2 * areal_mass_kg_m2 * velocity_m_s)


__all__ = ["PatchWeights", "RingLayout", "TransducerError", "averaging_weights", "equal_angles",
           "forcing_weights", "plane_wave_velocity_m_s", "rx_weights", "tone_burst", "tx_weights"]
