"""How strongly, and in which directions, a defect re-radiates an incident T(0,1) wave.

Each defect is a point scatterer on the unrolled pipe wall. Its far field, for a unit incident
plane wave, is ``S(phi) * sqrt(lambda / r) * exp(+i pi/4)`` (2-D cylindrical spreading; the
pi/4 phase lead undoes the lag that summing round the ring adds), where phi is the scattering angle from the incident direction and S is
complex (magnitude and phase of the scattered pulse). With this normalisation the part of the
scattered field that stays axisymmetric, i.e. the ring-averaged T(0,1) reflection coefficient
seen by a full ring, is ``R_T = S(pi) * lambda / C`` (stationary phase round the circumference).
Strength defaults are derived from the defect size; see docs/simulator.md for the assumptions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mocknode.scenario import DefectSpec, MassSize, NodeScenario, NotchSize, PipeSpec

MM_PER_M = 1000.0

# Mass loading: calibrated so that the paper's 10 kg clamp at 75 kHz, 200 mm from the Tx ring,
# lowers the direct T(0,1) arrival behind it by a few percent (paper, Table 3: 1-5 %).
MASS_REFERENCE_STRENGTH = 0.09
MASS_REFERENCE_KG = 10.0
MASS_REFERENCE_HZ = 75e3
MASS_MAX_STRENGTH = 0.8  # default strengths are capped here (mass_kg * frequency extrapolation)

_ANGLES_RAD = np.linspace(-math.pi, math.pi, 721)


@dataclass(frozen=True)
class ActiveDefect:
    """A defect present at some elapsed time, with its current far-field scattering amplitudes.

    ``back`` and ``forward`` are the complex amplitudes S(pi) and S(0) (notch); for a mass
    ``back == forward`` (monopole). ``width_mm`` is the circumferential extent that narrows the
    notch's sideways radiation.
    """

    kind: Literal["notch", "mass"]
    axial_mm: float
    angle_deg: float
    strength: float
    back: complex
    forward: complex
    width_mm: float


def notch_ring_reflection(size: NotchSize, pipe: PipeSpec, wavelength_mm: float) -> complex:
    """Ring-averaged T(0,1) reflection of a part-depth notch: two impedance steps, w apart.

    Each step reflects CSAL/2 (cross-section area loss over two), the exit step inverted and
    delayed by 2w/c; referred to the notch centre this is ``i * CSAL * sin(k w)``.
    """
    depth = min(size.depth_mm, pipe.wall_mm)
    mean_circ = pipe.propagation_circumference_mm
    circ = min(size.circumferential_mm, mean_circ)
    csal = circ * depth / (mean_circ * pipe.wall_mm)
    k = 2 * math.pi / wavelength_mm
    return 1j * csal * math.sin(k * size.axial_mm_len)


def notch_pattern(cos_scatter: np.ndarray, sin_out: np.ndarray, cos_out: np.ndarray,
                  width_mm: float, wavelength_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Back and forward lobe weights of a notch, including the receivers' shear polarisation.

    Cardioids (1 -/+ cos)/2 about the incident direction, times the array factor of a
    ``width_mm`` line source along the circumference, times |cos| of the arrival direction
    (a torsional receiver senses only the circumferential displacement of an SH wave).
    """
    shape = np.sinc(width_mm * sin_out / wavelength_mm) * np.abs(cos_out)
    return 0.5 * (1 - cos_scatter) * shape, 0.5 * (1 + cos_scatter) * shape


def mass_pattern(cos_out: np.ndarray) -> np.ndarray:
    """Point mass sheared circumferentially: an s-directed force radiates SH with u_s ~ cos^2."""
    return cos_out**2


def _notch_forward(back: complex, width_mm: float, wavelength_mm: float) -> complex:
    """Forward (shadow) amplitude from energy balance: the axisymmetric wave loses what is scattered.

    Ring-level optical theorem in this normalisation: -2 Re(S_f) = integral |S(phi)|^2 dphi.
    With the back lobe in quadrature (phase +-pi/2) and S_f real negative the cross term
    vanishes, leaving a S_f^2 + 2 S_f + b = 0 for S_f <= 0.
    """
    phi = _ANGLES_RAD
    w_back, w_fwd = notch_pattern(np.cos(phi), np.sin(phi), np.cos(phi), width_mm, wavelength_mm)
    a = float(np.trapezoid(w_fwd**2, phi))
    b = abs(back) ** 2 * float(np.trapezoid(w_back**2, phi))
    disc = max(1.0 - a * b, 0.0)
    return complex(-(1.0 - math.sqrt(disc)) / a)


def _mass_amplitude(strength: float) -> complex:
    """Clamped mass: ring-level forward and back coefficients real negative (extinction).

    A lossless point mass would only delay the wave (phase -pi/2) and, near the forward axis,
    focus it like a weak lens; the paper's clamp lowers the arrival behind it (Table 3), so the
    contact is taken as lossy. Locally (with the pi/4 lead) this is a reduction plus a delay.
    """
    return complex(-strength, 0.0)


def wavelength_mm(scn: NodeScenario) -> float:
    """T(0,1) wavelength at the excitation centre frequency and the nominal velocity."""
    return scn.pipe.velocity_m_s * MM_PER_M / scn.excitation.frequency_hz


def default_strength(defect: DefectSpec, scn: NodeScenario) -> float:
    """|S(back)| implied by the defect size at the excitation frequency (see module docstring)."""
    lam = wavelength_mm(scn)
    if isinstance(defect.size, NotchSize):
        r_t = notch_ring_reflection(defect.size, scn.pipe, lam)
        return abs(r_t) * scn.pipe.propagation_circumference_mm / lam
    assert isinstance(defect.size, MassSize)
    scale = (defect.size.mass_kg / MASS_REFERENCE_KG) * (scn.excitation.frequency_hz / MASS_REFERENCE_HZ)
    return min(MASS_REFERENCE_STRENGTH * scale, MASS_MAX_STRENGTH)


def strength_at(defect: DefectSpec, scn: NodeScenario, elapsed_s: float) -> float | None:
    """Current strength, or None when the defect has not appeared yet."""
    if elapsed_s < defect.appears_at_s:
        return None
    final = defect.strength if defect.strength is not None else default_strength(defect, scn)
    growth = defect.growth
    if growth is None:
        return final
    if growth.final_strength is not None:
        final = growth.final_strength
    frac = min((elapsed_s - defect.appears_at_s) / growth.grow_duration_s, 1.0)
    return growth.start_strength + (final - growth.start_strength) * frac


def activate(defect: DefectSpec, scn: NodeScenario, strength: float) -> ActiveDefect:
    """Complex back/forward amplitudes for a defect of the given |S(back)| (notch) or |S| (mass)."""
    lam = wavelength_mm(scn)
    if defect.kind == "notch":
        assert isinstance(defect.size, NotchSize)
        phase = 1j if notch_ring_reflection(defect.size, scn.pipe, lam).imag >= 0 else -1j
        back = strength * phase
        forward = _notch_forward(back, defect.size.circumferential_mm, lam) if strength > 0 else 0j
        width = defect.size.circumferential_mm
    else:
        assert isinstance(defect.size, MassSize)
        back = forward = _mass_amplitude(strength)
        width = defect.size.diameter_mm
    return ActiveDefect(defect.kind, defect.axial_mm, defect.angle_deg, strength, back, forward, width)


def defects_at(scn: NodeScenario, elapsed_s: float) -> list[ActiveDefect]:
    """The defects present ``elapsed_s`` into the scenario, with their strength at that time."""
    active = []
    for defect in scn.defects:
        strength = strength_at(defect, scn, elapsed_s)
        if strength is not None:
            active.append(activate(defect, scn, strength))
    return active
