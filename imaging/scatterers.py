"""Far-field scattering patterns of defects the echo fit can model beyond an isotropic point.

A heavy mass on the wall (a clamp, a support, a 1 kg weight on a 20 mm disc: 100x the 4 mm wall's areal
mass) hardly lets the wall under it move: a clamped (rigid) disc. For a torsional wave modelled as a 2-D
scalar (SH) field its scattered field is known exactly: the partial-wave series of a rigid cylinder. Its
pattern depends on k a (a the radius): nearly isotropic for k a << 1, and for k a ~ 1-2 (a 10 mm radius at
75-85 kHz) its amplitude falls by half towards 90 deg and its phase leads by about b (1 - cos psi), b ~ -k a.
An element-by-element incident field (a sparse Tx ring, imaging/paths.py) reaches a scatterer from many
directions at once, so such a pattern changes which of its terms the receivers hear, not only by how much:
on the project's own full-wave engine a 1 kg mass on 20 mm, 10 deg round from an 8-ring's receiver line,
leaves 0.74 of the record to the point's echo fit at its true position and 0.12 to the clamped disc's
(docs/imaging.md, "A strong scatterer on a sparse ring fitted as a clamped disc").
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import hankel1, jv

SERIES_EXTRA_ORDERS = 12  # partial waves beyond ka kept in the clamped disc's series (each next one is tiny)


def clamped_disc_pattern(ka: float, psi: np.ndarray) -> np.ndarray:
    """The far-field pattern f(psi) of a clamped (rigid, displacement-free) disc of radius a in a 2-D scalar (SH)
    field, k a = ``ka``, at scattering angles ``psi`` (rad; 0: forward): the exact partial-wave series
    f = sum_n eps_n A_n cos(n psi), A_n = -J_n(ka) / H1_n(ka), eps_0 = 1, eps_n = 2 (scattering by a rigid
    cylinder), for a unit plane wave exp(i k z) scattering into sqrt(2 / (pi k r)) exp(i (k r - pi / 4)) f(psi). The
    time factor is exp(-i w t): a more negative phase is a shorter path. Lossless: (1 / 2 pi) times the integral
    of |f|^2 over psi equals -Re f(0) (what the disc scatters it takes from the forward wave)."""
    if not ka > 0:
        raise ValueError(f"k a must be positive, got {ka}")
    n = np.arange(math.ceil(ka) + SERIES_EXTRA_ORDERS)
    terms = np.where(n == 0, 1.0, 2.0) * -jv(n, ka) / hankel1(n, ka)
    return np.cos(np.outer(np.asarray(psi, dtype=np.float64).ravel(), n)) @ terms


def disc_weights(radius_mm: float, wavelength_mm: float, cos_psi: np.ndarray) -> np.ndarray:
    """A clamped disc's pattern relative to its forward scattering, f(psi) / f(0), at scattering angles given by
    their cosines (any shape; the same shape out): the complex weight of each path's echo against an isotropic
    point's (a phase > 0 a carrier lagging). ``radius_mm`` 0: a point, 1 everywhere."""
    cos_psi = np.asarray(cos_psi, dtype=np.float64)
    if radius_mm == 0.0:
        return np.ones(cos_psi.shape, dtype=np.complex128)
    ka = 2.0 * math.pi * radius_mm / wavelength_mm
    pattern = clamped_disc_pattern(ka, np.arccos(np.clip(cos_psi, -1.0, 1.0)))
    return (pattern / clamped_disc_pattern(ka, np.zeros(1))[0]).reshape(cos_psi.shape)


__all__ = ["clamped_disc_pattern", "disc_weights"]
