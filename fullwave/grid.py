"""The finite-difference grid of the unrolled pipe wall, and where shapes fall on it.

Axial coordinate z (m) runs along the pipe, circumferential s (m) round it, periodic in the
circumference C. The wall is divided into ``nz x ns`` cells; the pipe itself covers the cells
``pml_cells .. pml_cells + n_pipe - 1`` exactly (its ends lie on cell faces), and with absorbing
ends ``pml_cells`` more cells of the same pipe continue beyond each end to hold the absorbing
layer (fullwave/absorber.py). Position 0 of ``pipe_z`` is the pipe end behind the Tx ring.

Shapes (transducer patches, notches, masses) are put on the grid as *coverage*: the fraction of
each control cell that the shape covers, so a shape's position and size are not rounded to
whole cells. Coverage is computed for any staggered position set (cells, or cells shifted half a
cell in z or s), because the velocity components of the in-plane model live on shifted grids.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DISC_SUBSAMPLES = 8  # per cell and direction, for the area of a disc in a cell


class GridError(ValueError):
    """A grid that cannot be built: non-positive sizes, a cell larger than the features it must hold."""


@dataclass(frozen=True)
class Grid:
    """``nz x ns`` cells of ``dz_m x ds_m``; ``pml_cells`` extra cells beyond each pipe end."""

    n_pipe: int
    ns: int
    dz_m: float
    ds_m: float
    pml_cells: int = 0

    def __post_init__(self) -> None:
        if self.n_pipe < 2 or self.ns < 1 or self.pml_cells < 0:
            raise GridError(f"grid needs n_pipe >= 2, ns >= 1, pml_cells >= 0 (got {self.n_pipe}, {self.ns}, "
                            f"{self.pml_cells})")
        if not (self.dz_m > 0 and self.ds_m > 0):
            raise GridError("cell sizes must be positive")

    @property
    def nz(self) -> int:
        return self.n_pipe + 2 * self.pml_cells

    @property
    def length_m(self) -> float:
        """Length of the pipe (the absorbing layers excluded)."""
        return self.n_pipe * self.dz_m

    @property
    def circumference_m(self) -> float:
        return self.ns * self.ds_m

    def cell_z_m(self) -> np.ndarray:
        """Pipe coordinate of every cell centre, [nz]."""
        return (np.arange(self.nz) - self.pml_cells + 0.5) * self.dz_m

    def face_z_m(self) -> np.ndarray:
        """Pipe coordinate of the nz + 1 faces between cells (the first and last are the grid's ends)."""
        return (np.arange(self.nz + 1) - self.pml_cells) * self.dz_m

    def cell_s_m(self, offset: float = 0.0) -> np.ndarray:
        """Circumferential position of every cell centre (``offset`` = 0.5: of the boundary after it), [ns]."""
        return (np.arange(self.ns) + 0.5 + offset) * self.ds_m


def make_grid(length_mm: float, circumference_mm: float, cell_mm: float, pml_mm: float = 0.0) -> Grid:
    """A grid of (close to) ``cell_mm`` square cells whose whole number of cells spans the pipe
    exactly in both directions (so dz and ds differ from ``cell_mm`` by under half a cell's worth)."""
    if not (cell_mm > 0 and length_mm > 0 and circumference_mm > 0 and pml_mm >= 0):
        raise GridError("length, circumference and cell size must be positive, the absorbing layer non-negative")
    n_pipe = max(2, round(length_mm / cell_mm))
    ns = max(1, round(circumference_mm / cell_mm))
    dz_mm = length_mm / n_pipe
    return Grid(n_pipe, ns, dz_mm * 1e-3, circumference_mm / ns * 1e-3, math.ceil(pml_mm / dz_mm - 1e-9))


def interval_overlap(lo: np.ndarray, hi: np.ndarray, a: float, b: float) -> np.ndarray:
    """Length of [lo, hi] intersected with [a, b], elementwise."""
    return np.clip(np.minimum(hi, b) - np.maximum(lo, a), 0.0, None)


def _periodic_overlap(lo: np.ndarray, hi: np.ndarray, a: float, b: float, period: float) -> np.ndarray:
    """Overlap of cells [lo, hi] with [a, b] on a circle of ``period`` (the interval may wrap)."""
    a0 = a % period
    shift = a0 - a
    total = np.zeros(np.shape(lo))
    for k in (-1, 0, 1):
        total += interval_overlap(lo, hi, a0 + k * period, b + shift + k * period)
    return total


def _z_centres(grid: Grid, on_faces: bool) -> np.ndarray:
    """Axial positions of the control cells: the nz cell centres, or the nz + 1 faces."""
    return grid.face_z_m() if on_faces else grid.cell_z_m()


def rectangle_coverage(grid: Grid, z0_m: float, z1_m: float, s0_m: float, s1_m: float,
                       on_faces: bool = False, s_offset: float = 0.0) -> np.ndarray:
    """Fraction of each control cell inside the rectangle z0..z1 x s0..s1 (s periodic).

    Control cells are dz x ds, centred on the cell centres (or, ``on_faces``, on the nz + 1 faces
    between cells in z) and on ``cell_s_m(s_offset)`` round the circumference.
    """
    zc, sc = _z_centres(grid, on_faces), grid.cell_s_m(s_offset)
    fz = interval_overlap(zc - grid.dz_m / 2, zc + grid.dz_m / 2, z0_m, z1_m) / grid.dz_m
    fs = _periodic_overlap(sc - grid.ds_m / 2, sc + grid.ds_m / 2, s0_m, s1_m, grid.circumference_m) / grid.ds_m
    return np.minimum(np.outer(fz, fs), 1.0)


def disc_coverage(grid: Grid, z_m: float, s_m: float, radius_m: float) -> np.ndarray:
    """Fraction of each cell [nz, ns] inside the disc (s periodic), by sub-sampling each cell near
    the disc on a ``DISC_SUBSAMPLES``-square lattice."""
    cover = np.zeros((grid.nz, grid.ns))
    zc, sc = grid.cell_z_m(), grid.cell_s_m()
    rows = np.flatnonzero(np.abs(zc - z_m) <= radius_m + grid.dz_m)
    circ = grid.circumference_m
    ds_wrapped = (sc - s_m + circ / 2) % circ - circ / 2  # signed distance round the circle
    cols = np.flatnonzero(np.abs(ds_wrapped) <= radius_m + grid.ds_m)
    sub = (np.arange(DISC_SUBSAMPLES) + 0.5) / DISC_SUBSAMPLES - 0.5
    for i in rows:
        dz = zc[i] - z_m + sub * grid.dz_m
        for j in cols:
            dsj = ds_wrapped[j] + sub * grid.ds_m
            cover[i, j] = np.mean(dz[:, None] ** 2 + dsj[None, :] ** 2 <= radius_m**2)
    return cover


__all__ = ["Grid", "GridError", "disc_coverage", "interval_overlap", "make_grid", "rectangle_coverage"]
