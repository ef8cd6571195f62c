"""Every way a scattered T(0,1) wave can travel from the Tx ring, via a point on the wall, to a receiver.

Unrolled wall: ``z`` axial mm from the Tx ring (the Rx ring at ``D = tx_rx_distance_mm``), ``s``
round the circumference (periodic). The Tx ring launches an axisymmetric plane wave both ways;
a pipe end reflects it (image method), so a point at z is hit by

- the direct wave, after |z|;
- the wave reflected at the near end (behind the Tx ring, at ``-A``), after 2A + z;
- the wave reflected at the far end (beyond the Rx ring, at ``F``), after 2F - z.

The point re-radiates a cylindrical wave; it reaches receiver m directly, or after reflecting
at the far end (image of the Rx ring at 2F - D) or the near end (image at -2A - D), each
either way round the pipe (two wraps). Expected amplitude of a path, per unit scatterer
strength: the ends' reflection coefficients, 2-D spreading sqrt(lambda / r) (softened within
half a wavelength), and, for torsional (circumferentially polarised) receivers, |cos| of the
arrival direction from the pipe axis: an SH wave arriving at angle phi moves the wall
circumferentially by cos(phi).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


class PathModelError(ValueError):
    """A path model's geometry is inconsistent (e.g. an end between the rings)."""


@dataclass(frozen=True)
class PathFamily:
    """Incident length |in_offset_mm + in_sign * z|; outgoing from z to the Rx image at ``rx_image_mm``.

    ``factor`` is the product of the end reflection coefficients met on the way.
    """

    name: str
    in_offset_mm: float
    in_sign: float
    rx_image_mm: float
    factor: float


@dataclass(frozen=True)
class PathModel:
    """Geometry and amplitude model of the scattered paths (hashable: it keys the gather-table cache).

    ``circumference_mm`` is the wrap length the scattered wave travels round the pipe (the
    mid-wall circumference when the wall thickness is known). ``near_end_mm``/``far_end_mm``
    are the pipe ends' axial positions from the Tx ring (None: unknown, not modelled).
    ``wraps`` 1 keeps only the shorter way round, 2 both. Paths whose end-reflection factor is
    below ``min_factor`` are dropped (e.g. every end path of a pipe with absorbing ends).
    """

    tx_rx_distance_mm: float
    circumference_mm: float
    wavelength_mm: float
    near_end_mm: float | None = None
    far_end_mm: float | None = None
    near_reflection: float = 0.0
    far_reflection: float = 0.0
    polarization: bool = True
    wraps: int = 2
    min_factor: float = 0.05

    def __post_init__(self) -> None:
        if not (self.tx_rx_distance_mm > 0 and self.circumference_mm > 0 and self.wavelength_mm > 0):
            raise PathModelError("distances and wavelength must be positive")
        if self.wraps not in (1, 2):
            raise PathModelError(f"wraps must be 1 or 2, got {self.wraps}")
        if self.near_end_mm is not None and self.near_end_mm > 0:
            raise PathModelError("the near end lies behind the Tx ring (near_end_mm <= 0)")
        if self.far_end_mm is not None and self.far_end_mm < self.tx_rx_distance_mm:
            raise PathModelError("the far end lies beyond the Rx ring (far_end_mm >= tx_rx_distance_mm)")

    def families(self) -> tuple[PathFamily, ...]:
        """The incident x outgoing combinations kept by this model, direct-direct first."""
        d = self.tx_rx_distance_mm
        incident = [("direct", 0.0, 1.0, 1.0)]
        outgoing = [("direct", d, 1.0)]
        if self.near_end_mm is not None:
            incident.append(("near", -2.0 * self.near_end_mm, 1.0, self.near_reflection))
            outgoing.append(("near", 2.0 * self.near_end_mm - d, self.near_reflection))
        if self.far_end_mm is not None:
            incident.append(("far", 2.0 * self.far_end_mm, -1.0, self.far_reflection))
            outgoing.append(("far", 2.0 * self.far_end_mm - d, self.far_reflection))
        out = []
        for in_name, offset, sign, r_in in incident:
            for out_name, image, r_out in outgoing:
                factor = r_in * r_out
                if factor >= self.min_factor:
                    out.append(PathFamily(f"{in_name}>{out_name}", offset, sign, image, factor))
        return tuple(out)


def coherence_groups(model: PathModel) -> int:
    """Number of groups summed coherently: one per path family and way round the pipe.

    A defect's scattered phase depends on the direction it radiates in (forward, back, or
    round the pipe one way or the other), so only paths leaving it in the same kind of
    direction are added with their phase; the groups are then added in power.
    """
    return len(model.families()) * model.wraps


def signed_arc_mm(rel_angle_deg: np.ndarray, circumference_mm: float) -> np.ndarray:
    """Signed circumferential offset in (-C/2, C/2] for an angle difference in degrees."""
    wrapped = np.mod(np.asarray(rel_angle_deg, dtype=np.float64) + 180.0, 360.0) - 180.0
    wrapped = np.where(wrapped == -180.0, 180.0, wrapped)
    return wrapped * (circumference_mm / 360.0)


def wrap_offsets_mm(arc_mm: np.ndarray, circumference_mm: float, wraps: int) -> list[np.ndarray]:
    """The circumferential legs to take: the shorter way round, and (wraps=2) the other way."""
    legs = [arc_mm]
    if wraps == 2:
        legs.append(arc_mm - np.where(arc_mm >= 0, 1.0, -1.0) * circumference_mm)
    return legs


def path_weight(factor: float | np.ndarray, dz_mm: np.ndarray, r_mm: np.ndarray, model: PathModel) -> np.ndarray:
    """Expected amplitude per unit strength: factor * sqrt(lambda / max(r, lambda/2)) * |cos(arrival)|."""
    lam = model.wavelength_mm
    w = factor * np.sqrt(lam / np.maximum(r_mm, 0.5 * lam))
    if model.polarization:
        w = w * np.where(r_mm > 0, np.abs(dz_mm) / np.where(r_mm > 0, r_mm, 1.0), 1.0)
    return w


def scatter_paths(
    model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(coherence group, length_mm, weight) of every modelled path, broadcast over axial_mm x rel_angle_deg.

    ``rel_angle_deg`` is the pixel angle minus the receiver angle. The group is
    ``family_index * wraps + wrap`` (see ``coherence_groups``).
    """
    z = np.asarray(axial_mm, dtype=np.float64)
    arc = signed_arc_mm(rel_angle_deg, model.circumference_mm)
    paths = []
    for f, fam in enumerate(model.families()):
        incident = np.abs(fam.in_offset_mm + fam.in_sign * z)
        dz = fam.rx_image_mm - z
        for wrap, leg in enumerate(wrap_offsets_mm(arc, model.circumference_mm, model.wraps)):
            r = np.hypot(dz, leg)
            length, weight = np.broadcast_arrays(incident + r, path_weight(fam.factor, dz, r, model))
            paths.append((f * model.wraps + wrap, length, weight))
    return paths


def stacked_paths(
    model: PathModel, axial_mm: np.ndarray, rel_angle_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``scatter_paths`` as three arrays: groups [P] (int64), length_mm and weight [P, *broadcast shape].

    The same arithmetic, done once for all families and wraps (few large array operations
    instead of many small ones: what a small grid needs).
    """
    families = model.families()
    if not families:
        shape = np.broadcast_shapes(np.shape(axial_mm), np.shape(rel_angle_deg))
        return np.zeros(0, np.int64), np.zeros((0,) + shape), np.zeros((0,) + shape)
    z = np.asarray(axial_mm, dtype=np.float64)
    arc = signed_arc_mm(rel_angle_deg, model.circumference_mm)
    legs = np.stack(np.broadcast_arrays(*wrap_offsets_mm(arc, model.circumference_mm, model.wraps)))  # [W, ...]
    extra = (1,) * max(z.ndim, legs.ndim - 1)
    offset, sign, image, factor = (np.array([getattr(f, name) for f in families]).reshape((-1, 1) + extra)
                                   for name in ("in_offset_mm", "in_sign", "rx_image_mm", "factor"))
    incident = np.abs(offset + sign * z)  # [F, 1, ...]
    dz = image - z
    # sqrt of the sum of squares, not np.hypot (~20x slower here); lengths are mm, far from overflow.
    r = np.sqrt(np.square(dz) + np.square(legs[None]))  # [F, W, ...]
    length = incident + r
    weight = path_weight(factor, dz, r, model)
    length, weight = np.broadcast_arrays(length, weight)
    n = len(families) * model.wraps
    groups = np.arange(n, dtype=np.int64)
    return groups, length.reshape((n,) + length.shape[2:]), weight.reshape((n,) + weight.shape[2:])


def scalar_paths(model: PathModel, z_mm: float, rel_angle_deg: float) -> list[tuple[int, float, float]]:
    """The same paths for one pixel, written out with scalar math (the literal oracle's model)."""
    lam, circ = model.wavelength_mm, model.circumference_mm
    diff = (rel_angle_deg + 180.0) % 360.0 - 180.0
    if diff == -180.0:
        diff = 180.0
    arc = diff * circ / 360.0
    legs = [arc] if model.wraps == 1 else [arc, arc - (1.0 if arc >= 0 else -1.0) * circ]
    out = []
    for f, fam in enumerate(model.families()):
        incident = abs(fam.in_offset_mm + fam.in_sign * z_mm)
        dz = fam.rx_image_mm - z_mm
        for wrap, leg in enumerate(legs):
            r = math.hypot(dz, leg)
            w = fam.factor * math.sqrt(lam / max(r, 0.5 * lam))
            if model.polarization and r > 0:
                w *= abs(dz) / r
            out.append((f * model.wraps + wrap, incident + r, w))
    return out
