"""Dispersion of the pipe's other guided modes: plate Lamb/SH modes wound helically round the pipe.

The approximation (documented with its errors in docs/simulator.md, "Other guided modes"):

* The pipe wall is a free isotropic plate of the wall thickness. Its three fundamental modes
  are found exactly from the Rayleigh-Lamb equations: A0 (antisymmetric, dispersive), S0
  (symmetric, nearly non-dispersive at these frequency-thicknesses) and SH0 (= c_T, exact).
* A pipe mode of circumferential order n is that plate mode travelling helically on the
  mid-wall cylinder of radius R: its wavenumber splits into n/R round the pipe and
  ``k_z = sqrt(k_plate(f)^2 - (n/R)^2)`` along it. Families (the usual pipe labels):
  m=1 L(0,1), F(n,1) from A0; m=2 T(0,1), F(n,2) from SH0; m=3 L(0,2), F(n,3) from S0.
  Below the cut-off ``k_plate(f) = n/R`` the mode is evanescent: ``k_z = -i kappa``.

This is the "unrolled plate" limit: it neglects curvature (terms of order (t/R)^2 ~ 0.5 % for
the paper's pipe, more near cut-off) and the coupling between families that curvature
causes (the real F(n,m) modes mix polarisations near their cut-offs). Pure functions, no
state but an LRU cache of the plate tables.
"""
from __future__ import annotations

import math
import re
from functools import lru_cache

import numpy as np
from scipy.interpolate import CubicSpline

FAMILIES = {1: "A0", 2: "SH0", 3: "S0"}
TABLE_MAX_HZ = 600e3  # plate tables cover 0..600 kHz (below the A1 cut-off of a 4 mm steel wall,
TABLE_STEP_HZ = 1000.0  # 391 kHz, only the fundamental modes exist; above it they still continue)

_MODE = re.compile(r"^\s*(?:(L)\(0,([12])\)|(T)\(0,1\)|(F)\((\d+),([123])\))\s*$")


class DispersionError(ValueError):
    """A mode name or material constant is invalid."""


def parse_mode(name: str) -> tuple[int, int]:
    """``"L(0,1)"`` -> (0, 1), ``"L(0,2)"`` -> (0, 3), ``"T(0,1)"`` -> (0, 2), ``"F(8,2)"`` -> (8, 2): (order n, family m)."""
    match = _MODE.match(name)
    if match is None:
        raise DispersionError(f"unknown mode {name!r}: use L(0,1), L(0,2), T(0,1) or F(n,m) with m in 1..3")
    if match.group(1):
        return 0, 1 if match.group(2) == "1" else 3
    if match.group(3):
        return 0, 2
    order, family = int(match.group(5)), int(match.group(6))
    if order < 1:
        raise DispersionError(f"{name!r}: a flexural mode has order n >= 1 (n = 0 is L(0,1), T(0,1) or L(0,2))")
    return order, family


def bulk_velocities(shear_m_s: float, poisson: float) -> tuple[float, float]:
    """(c_L, c_T) in m/s of an isotropic solid with shear velocity c_T and Poisson's ratio nu."""
    if not 0.0 < poisson < 0.5:
        raise DispersionError(f"Poisson's ratio must be in (0, 0.5), got {poisson}")
    return shear_m_s * math.sqrt(2 * (1 - poisson) / (1 - 2 * poisson)), shear_m_s


def _rayleigh_lamb(c: np.ndarray, omega: np.ndarray, half_mm: float, c_l: float, c_t: float,
                   symmetric: bool) -> np.ndarray:
    """Real-valued Rayleigh-Lamb function of phase velocity c (m/s) at omega (rad/s); zero on a mode.

    Symmetric: (q^2-k^2)^2 cos(ph) sin(qh)/q + 4 k^2 p sin(ph) cos(qh);
    antisymmetric: (q^2-k^2)^2 sin(ph)/p cos(qh) + 4 k^2 q sin(qh) cos(ph). Every factor is an
    even function of p and q, so it stays real when p or q is imaginary (c below c_L or c_T).
    """
    h = half_mm * 1e-3
    k = omega / c
    p2 = (omega / c_l) ** 2 - k**2
    q2 = (omega / c_t) ** 2 - k**2

    # Each term has one p-factor and one q-factor; an imaginary p or q (cosh, sinh) is divided by
    # exp(|x| h), a positive factor common to both terms, so the sign is kept and nothing overflows.
    def parts(x2):
        a = np.sqrt(np.abs(x2))
        real = x2 >= 0
        decay = np.exp(-2.0 * np.where(real, 0.0, a) * h)
        cos_ = np.where(real, np.cos(a * h), 0.5 * (1 + decay))
        sinh_ = 0.5 * (1 - decay)
        safe = np.where(a > 0, a, 1.0)
        sin_over = np.where(a == 0, h, np.where(real, np.sin(a * h), sinh_) / safe)  # sin(x h) / x
        x_sin = np.where(real, a * np.sin(a * h), -a * sinh_)  # x sin(x h)
        return cos_, sin_over, x_sin

    cos_p, sin_over_p, x_sin_p = parts(p2)
    cos_q, sin_over_q, x_sin_q = parts(q2)
    lead = (q2 - k**2) ** 2
    if symmetric:
        return lead * cos_p * sin_over_q + 4 * k**2 * x_sin_p * cos_q
    return lead * sin_over_p * cos_q + 4 * k**2 * x_sin_q * cos_p


def _lamb_phase_velocity(freqs_hz: np.ndarray, thickness_mm: float, c_l: float, c_t: float,
                         symmetric: bool) -> np.ndarray:
    """Phase velocity (m/s) of A0 (symmetric False) or S0 at each frequency > 0: bracket and bisect."""
    omega = 2 * math.pi * freqs_hz[:, None]
    if symmetric:  # S0 lies between the Rayleigh velocity (~0.92 c_T) and c_L
        grid = np.linspace(0.85 * c_t, c_l * (1 - 1e-9), 400)[None, :]
    else:  # A0 lies below the Rayleigh velocity
        grid = np.linspace(1.0, 0.95 * c_t, 400)[None, :]
    vals = _rayleigh_lamb(grid, omega, thickness_mm / 2, c_l, c_t, symmetric)
    change = np.signbit(vals[:, :-1]) != np.signbit(vals[:, 1:])
    # S0: the fastest root below c_L; A0: the slowest root.
    j = change.shape[1] - 1 - np.argmax(change[:, ::-1], axis=1) if symmetric else np.argmax(change, axis=1)
    if not np.all(change[np.arange(change.shape[0]), j]):
        raise DispersionError("a plate mode was not bracketed (frequency too high for the table?)")
    lo, hi = grid[0, j].copy(), grid[0, j + 1].copy()
    w = omega[:, 0]
    f_lo = _rayleigh_lamb(lo, w, thickness_mm / 2, c_l, c_t, symmetric)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        f_mid = _rayleigh_lamb(mid, w, thickness_mm / 2, c_l, c_t, symmetric)
        same = np.signbit(f_mid) == np.signbit(f_lo)
        lo, f_lo = np.where(same, mid, lo), np.where(same, f_mid, f_lo)
        hi = np.where(same, hi, mid)
    return 0.5 * (lo + hi)


@lru_cache(maxsize=16)
def plate_table(family: int, thickness_mm: float, shear_m_s: float, poisson: float) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies Hz, wavenumber rad/mm) of a plate mode on a 1 kHz grid from 0 to 600 kHz (read-only).

    Roots are bisected to ~1e-12 relative; between grid points ``plate_wavenumber`` uses a cubic
    spline (A0: within 3e-6 rad/mm of a 250 Hz table above 5 kHz, i.e. 0.01 rad of phase over 3 m).
    """
    if family not in FAMILIES:
        raise DispersionError(f"family must be 1, 2 or 3, got {family}")
    c_l, c_t = bulk_velocities(shear_m_s, poisson)
    f = np.arange(0.0, TABLE_MAX_HZ + TABLE_STEP_HZ / 2, TABLE_STEP_HZ)
    k = np.zeros_like(f)
    if family == 2:
        k = 2 * math.pi * f / c_t
    else:
        c = _lamb_phase_velocity(f[1:], thickness_mm, c_l, c_t, symmetric=family == 3)
        k[1:] = 2 * math.pi * f[1:] / c
    k = k / 1000.0  # rad/m -> rad/mm
    f.setflags(write=False)
    k.setflags(write=False)
    return f, k


@lru_cache(maxsize=16)
def _plate_spline(family: int, thickness_mm: float, shear_m_s: float, poisson: float) -> CubicSpline:
    return CubicSpline(*plate_table(family, thickness_mm, shear_m_s, poisson))


def plate_wavenumber(family: int, freqs_hz: np.ndarray, thickness_mm: float, shear_m_s: float,
                     poisson: float) -> np.ndarray:
    """Plate wavenumber (rad/mm) at each frequency (cubic spline through the 1 kHz table;
    frequencies beyond 600 kHz are extrapolated at the last phase velocity)."""
    key = (family, float(thickness_mm), float(shear_m_s), float(poisson))
    f_tab, k_tab = plate_table(*key)
    f = np.abs(np.asarray(freqs_hz, dtype=np.float64))
    k = _plate_spline(*key)(np.minimum(f, f_tab[-1]))
    beyond = f > f_tab[-1]
    if np.any(beyond):
        k = np.where(beyond, f * (k_tab[-1] / f_tab[-1]), k)
    return k


def axial_wavenumber(order: int, family: int, freqs_hz: np.ndarray, *, thickness_mm: float,
                     mid_radius_mm: float, shear_m_s: float, poisson: float,
                     velocity_scale: float = 1.0) -> np.ndarray:
    """Complex axial wavenumber k_z (rad/mm) of pipe mode (n, m); Im k_z <= 0 (evanescent below cut-off).

    ``velocity_scale`` s scales every bulk velocity (temperature): the plate relation
    omega(k) scales by s, so k_plate,s(f) = k_plate(f / s); the geometry term n/R does not.
    """
    kp = plate_wavenumber(family, np.asarray(freqs_hz, dtype=np.float64) / velocity_scale, thickness_mm,
                          shear_m_s, poisson)
    arg = kp**2 - (order / mid_radius_mm) ** 2
    root = np.sqrt(np.abs(arg))
    return np.where(arg >= 0, root + 0j, -1j * root)


def group_velocity_m_s(order: int, family: int, freqs_hz: np.ndarray, **geometry) -> np.ndarray:
    """Axial group velocity d omega / d k_z (m/s) of pipe mode (n, m); 0 where it is evanescent."""
    f = np.asarray(freqs_hz, dtype=np.float64)
    df = 10.0
    k_hi = axial_wavenumber(order, family, f + df, **geometry)
    k_lo = axial_wavenumber(order, family, np.maximum(f - df, 0.0), **geometry)
    dk = (k_hi.real - k_lo.real) * 1000.0  # rad/m
    span = 2 * math.pi * (f + df - np.maximum(f - df, 0.0))
    ok = (k_lo.imag == 0) & (k_hi.imag == 0) & (dk > 0)
    return np.where(ok, span / np.where(ok, dk, 1.0), 0.0)


def cutoff_hz(order: int, family: int, *, thickness_mm: float, mid_radius_mm: float, shear_m_s: float,
              poisson: float) -> float:
    """Frequency below which pipe mode (n, m) is evanescent in this approximation (0 for n = 0)."""
    if order == 0:
        return 0.0
    f_tab, k_tab = plate_table(family, float(thickness_mm), float(shear_m_s), float(poisson))
    target = order / mid_radius_mm
    if target > k_tab[-1]:
        return float(f_tab[-1] * target / k_tab[-1])
    return float(np.interp(target, k_tab, f_tab))  # k rises monotonically with f for these modes
