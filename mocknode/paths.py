"""Ray paths on the unrolled pipe wall: image sources for the two pipe ends, wraps round the pipe.

Axial coordinate z (mm) from the Tx ring, circumferential s (mm, periodic with the circumference).
A pipe end reflects T(0,1) with coefficient R; the image method replaces each end by mirrored
sources. Every function returns path lengths and amplitudes only; time and waveform live in
mocknode/physics.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mocknode.scattering import ActiveDefect, mass_pattern, notch_pattern

WRAPS = np.arange(-2, 3)  # both ways round the circumference, and once more each way
MIN_AMPLITUDE = 1e-7  # arrivals weaker than this (relative to the direct wave) are dropped


@dataclass(frozen=True)
class Arrivals:
    """Arrivals at each receiver, arrays [n_rx, n_paths] (padded with zero amplitude).

    ``path_mm`` total travel distance; ``amplitude`` complex (phase = constant phase shift of the
    pulse); ``sin_arrival``/``cos_arrival`` the direction the wave arrives from, relative to the
    pipe axis, used for the receiver aperture.
    """

    path_mm: np.ndarray
    amplitude: np.ndarray
    sin_arrival: np.ndarray
    cos_arrival: np.ndarray

    @staticmethod
    def concat(parts: list[Arrivals]) -> Arrivals:
        return Arrivals(*(np.concatenate([getattr(p, f) for p in parts], axis=1)
                          for f in ("path_mm", "amplitude", "sin_arrival", "cos_arrival")))


def image_points(z_mm: float, near_end_mm: float, far_end_mm: float, reflection: float,
                 max_distance_mm: float, from_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Images of a point at ``z_mm`` between two reflecting ends, within ``max_distance_mm`` of ``from_mm``.

    Images are z + 2nP (2|n| reflections) and 2*near_end - z + 2nP (|2n-1| reflections), P the
    pipe length. Returns (positions, amplitude R**reflections), strongest-first order not implied.
    """
    period = 2.0 * (far_end_mm - near_end_mm)
    n_max = math.ceil(max_distance_mm / period) + 1
    n = np.arange(-n_max, n_max + 1)
    pos = np.concatenate([z_mm + n * period, 2 * near_end_mm - z_mm + n * period])
    bounces = np.concatenate([2 * np.abs(n), np.abs(2 * n - 1)])
    amp = np.power(float(reflection), bounces)
    keep = (np.abs(pos - from_mm) <= max_distance_mm) & (amp >= MIN_AMPLITUDE)
    return pos[keep], amp[keep]


def direct_arrivals(n_rx: int, rx_axial_mm: float, near_end_mm: float, far_end_mm: float,
                    reflection: float, max_path_mm: float) -> Arrivals:
    """The axisymmetric wave from the Tx ring (z=0) at the Rx ring: direct and end reflections."""
    pos, amp = image_points(0.0, near_end_mm, far_end_mm, reflection, max_path_mm, rx_axial_mm)
    path = np.abs(rx_axial_mm - pos)
    ones = np.ones((n_rx, 1))
    return Arrivals(ones * path, ones * amp.astype(complex), np.zeros((n_rx, path.size)), ones * np.ones(path.size))


def scattered_arrivals(defect: ActiveDefect, rx_s_mm: np.ndarray, rx_axial_mm: float,
                       near_end_mm: float, far_end_mm: float, reflection: float,
                       circumference_mm: float, wavelength_mm: float, max_path_mm: float) -> Arrivals:
    """Every incident plane wave hits the defect, which re-radiates to every receiver image and wrap.

    Incident waves: images of the Tx ring (plane, no spreading). Outgoing: images of the Rx ring
    about the ends, times wraps k*C round the circumference, with cylindrical spreading.
    """
    z_d = defect.axial_mm
    s_d = defect.angle_deg / 360.0 * circumference_mm
    z_in, a_in = image_points(0.0, near_end_mm, far_end_mm, reflection, max_path_mm, z_d)
    path_in = np.abs(z_d - z_in)
    dir_in = np.where(z_d >= z_in, 1.0, -1.0)
    z_out, a_out = image_points(rx_axial_mm, near_end_mm, far_end_mm, reflection, max_path_mm, z_d)

    # Broadcast shape: [n_rx, n_in, n_out, n_wrap]
    dz = (z_out - z_d)[None, None, :, None]
    ds = (rx_s_mm[:, None, None, None] - s_d) + WRAPS[None, None, None, :] * circumference_mm
    r = np.hypot(dz, ds)
    safe_r = np.where(r > 0, r, 1.0)
    cos_out = np.where(r > 0, dz / safe_r, 1.0)
    sin_out = np.where(r > 0, ds / safe_r, 0.0)
    cos_scatter = dir_in[None, :, None, None] * cos_out
    if defect.kind == "notch":
        w_back, w_fwd = notch_pattern(cos_scatter, sin_out, cos_out, defect.width_mm, wavelength_mm)
        pattern = defect.back * w_back + defect.forward * w_fwd
    else:
        pattern = defect.back * mass_pattern(cos_out) * np.ones_like(cos_scatter)
    # 2-D far-field spreading. S is normalised to the ring-level (1-D) response, and summing a
    # 2-D field round the ring lags it by pi/4 (stationary phase), so the local field leads by pi/4.
    # r is softened within half a wavelength so a receiver on top of a scatterer stays finite.
    spreading = np.sqrt(wavelength_mm / np.hypot(r, 0.5 * wavelength_mm)) * np.exp(0.25j * math.pi)
    amp = (a_in[None, :, None, None] * a_out[None, None, :, None]) * pattern * spreading
    path = path_in[None, :, None, None] + r

    n_rx = rx_s_mm.size
    path, amp = path.reshape(n_rx, -1), amp.reshape(n_rx, -1)
    cos_a = np.broadcast_to(cos_out, cos_scatter.shape).reshape(n_rx, -1)
    sin_a = np.broadcast_to(sin_out, cos_scatter.shape).reshape(n_rx, -1)
    keep = np.any((path <= max_path_mm) & (np.abs(amp) >= MIN_AMPLITUDE), axis=0)
    amp = np.where(path <= max_path_mm, amp, 0.0)
    return Arrivals(path[:, keep], amp[:, keep], sin_a[:, keep], cos_a[:, keep])
