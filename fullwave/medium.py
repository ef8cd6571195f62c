"""The pipe wall as fields on the grid: thickness, areal mass and elastic moduli per cell.

The wall is a membrane of thickness h(z, s): its areal mass is rho h plus any added areal mass
(a clamp), its shear stiffness per unit width mu h, its in-plane (plane-stress) stiffness
E h / (1 - nu^2). Temperature scales the moduli (not the density): both bulk wave speeds change
by ``velocity_temp_coeff_per_c`` per degC, c(T) = c(T_ref) (1 + k (T - T_ref)), i.e. the
moduli by (1 + k dT)^2. Thermal expansion (1.2e-5 /K, ten times smaller) is not modelled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fullwave.grid import Grid


class MediumError(ValueError):
    """Material or temperature values that give no physical medium."""


@dataclass(frozen=True)
class Steel:
    """Isotropic elastic wall material; defaults: the paper's steel (Table 1)."""

    density_kg_m3: float = 7850.0
    youngs_modulus_pa: float = 200e9
    poisson_ratio: float = 0.3

    def __post_init__(self) -> None:
        if not (self.density_kg_m3 > 0 and self.youngs_modulus_pa > 0 and 0 <= self.poisson_ratio < 0.5):
            raise MediumError("density and Young's modulus must be positive, Poisson's ratio in [0, 0.5)")

    @property
    def shear_modulus_pa(self) -> float:
        return self.youngs_modulus_pa / (2 * (1 + self.poisson_ratio))

    @property
    def shear_velocity_m_s(self) -> float:
        """SH0 (torsional T(0,1)) velocity, non-dispersive: sqrt(mu / rho) (3130.4 m/s for the paper's steel)."""
        return math.sqrt(self.shear_modulus_pa / self.density_kg_m3)

    @property
    def plate_velocity_m_s(self) -> float:
        """S0 low-frequency (plane-stress) velocity sqrt(E / (rho (1 - nu^2))) (5290 m/s for the paper's steel)."""
        return math.sqrt(self.youngs_modulus_pa / (self.density_kg_m3 * (1 - self.poisson_ratio**2)))


def modulus_scale(temperature_c: float, reference_c: float, velocity_temp_coeff_per_c: float) -> float:
    """Factor on the moduli at ``temperature_c``: (1 + k (T - T_ref))^2, so wave speeds scale by 1 + k dT."""
    speed = 1.0 + velocity_temp_coeff_per_c * (temperature_c - reference_c)
    if not (math.isfinite(speed) and speed > 0.5):
        raise MediumError(f"temperature {temperature_c} degC scales the wave speed by {speed}: not physical")
    return speed * speed


@dataclass(frozen=True)
class Medium:
    """Cell-centred fields [nz, ns] of the wall on ``grid``; the moduli already at temperature."""

    grid: Grid
    thickness_m: np.ndarray
    areal_mass_kg_m2: np.ndarray
    shear_modulus_pa: float
    youngs_modulus_pa: float
    poisson_ratio: float

    @property
    def shear_stiffness_n_m(self) -> np.ndarray:
        """mu h per cell (N/m)."""
        return self.shear_modulus_pa * self.thickness_m

    @property
    def max_velocity_m_s(self) -> float:
        """Fastest wave anywhere (the plate velocity of the in-plane model; an added mass only slows)."""
        rho_h = self.areal_mass_kg_m2
        stiffness = self.youngs_modulus_pa / (1 - self.poisson_ratio**2) * self.thickness_m
        return float(np.sqrt(np.max(stiffness / rho_h)))

    @property
    def max_shear_velocity_m_s(self) -> float:
        return float(np.sqrt(np.max(self.shear_stiffness_n_m / self.areal_mass_kg_m2)))


def uniform_medium(grid: Grid, wall_m: float, steel: Steel, modulus_factor: float = 1.0) -> Medium:
    """The defect-free pipe wall: constant thickness ``wall_m``, moduli times ``modulus_factor``."""
    if not wall_m > 0:
        raise MediumError("the wall thickness must be positive")
    shape = (grid.nz, grid.ns)
    return Medium(
        grid=grid,
        thickness_m=np.full(shape, wall_m),
        areal_mass_kg_m2=np.full(shape, steel.density_kg_m3 * wall_m),
        shear_modulus_pa=steel.shear_modulus_pa * modulus_factor,
        youngs_modulus_pa=steel.youngs_modulus_pa * modulus_factor,
        poisson_ratio=steel.poisson_ratio,
    )


def harmonic_mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """2ab / (a + b), and 0 where either is 0: the stiffness of two springs in series, per unit length."""
    total = a + b
    return np.divide(2 * a * b, total, out=np.zeros(np.broadcast(a, b).shape), where=total > 0)


__all__ = ["Medium", "MediumError", "Steel", "harmonic_mean", "modulus_scale", "uniform_medium"]
