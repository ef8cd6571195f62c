"""The staggered leapfrog scheme's time step and numerical dispersion (second order in space and time).

Both kernels step at ``courant`` times the stability limit c dt sqrt(1/dz^2 + 1/ds^2) = 1 of
their fastest wave.

A plane wave exp(i (k.x - omega t)) on the grid obeys

    sin^2(omega dt / 2) / (c dt / 2)^2 = sin^2(k_z dz / 2) / (dz / 2)^2 + sin^2(k_s ds / 2) / (ds / 2)^2,

for every wave speed c of the model (SH0, and S0 in the in-plane model). Solved here for k at a
given frequency, which gives the grid's phase and group velocities: slightly below c, the more
so the fewer cells per wavelength. These are the figures docs/fullwave.md quotes.
"""
from __future__ import annotations

import math

from scipy.optimize import brentq


def stable_dt_s(dz_m: float, ds_m: float, velocity_m_s: float, courant: float) -> float:
    """The time step at ``courant`` times the 2-D leapfrog limit 1 / (c sqrt(1/dz^2 + 1/ds^2))."""
    return courant / (velocity_m_s * math.sqrt(1 / dz_m**2 + 1 / ds_m**2))


def _omega(k: float, c: float, dz: float, ds: float, dt: float, cos_a: float, sin_a: float) -> float:
    rhs = (math.sin(k * cos_a * dz / 2) / (dz / 2)) ** 2 + (math.sin(k * sin_a * ds / 2) / (ds / 2)) ** 2
    return 2 / dt * math.asin(min(1.0, c * dt / 2 * math.sqrt(rhs)))


def numerical_velocities(frequency_hz: float, velocity_m_s: float, dz_m: float, ds_m: float, dt_s: float,
                         angle_deg: float = 0.0) -> tuple[float, float]:
    """(phase, group) velocity in m/s on the grid of a wave at ``angle_deg`` from the pipe axis."""
    a = math.radians(angle_deg)
    cos_a, sin_a = math.cos(a), math.sin(a)
    omega = 2 * math.pi * frequency_hz
    k_exact = omega / velocity_m_s
    k = brentq(lambda q: _omega(q, velocity_m_s, dz_m, ds_m, dt_s, cos_a, sin_a) - omega, 0.5 * k_exact,
               min(2.0 * k_exact, 0.999 * math.pi / max(dz_m, ds_m)))
    h = 1e-6 * k
    group = (_omega(k + h, velocity_m_s, dz_m, ds_m, dt_s, cos_a, sin_a)
             - _omega(k - h, velocity_m_s, dz_m, ds_m, dt_s, cos_a, sin_a)) / (2 * h)
    return omega / k, group


__all__ = ["numerical_velocities", "stable_dt_s"]
