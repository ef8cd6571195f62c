"""Guided modes besides T(0,1): ring leakage (L(0,1), L(0,2), F(n,m)) and mode conversion at defects.

Opt-in through ``NodeScenario.modes`` (default: nothing, and the simulator's output is then
bit-identical to the T(0,1)-only model). Each mode travels along the pipe only (a mode of
circumferential order n has the fixed pattern cos(n theta) round the pipe), with the axial
wavenumber k_z(f) of mocknode/dispersion.py, so a dispersive pulse spreads and an evanescent
one dies away. Pipe ends reflect every mode with the pipe's T(0,1) coefficient (image method,
mocknode/paths.py). Rendered in the frequency domain on its own FFT, four record lengths
long; frequency components whose group delay would reach past that horizon (the slow part of
a mode near its cut-off) are tapered to zero instead of wrapping round into the record.
Model and assumptions: docs/simulator.md, "Other guided modes".
"""
from __future__ import annotations

import math

import numpy as np
from scipy import fft as sp_fft

from mocknode.dispersion import axial_wavenumber, bulk_velocities, parse_mode
from mocknode.paths import image_points
from mocknode.scattering import MM_PER_M, ActiveDefect, wavelength_mm
from mocknode.scenario import NodeScenario

SPECTRUM_FLOOR = 1e-5  # as mocknode/physics.py
HORIZON_RECORDS = 4  # the modes' FFT spans this many record lengths (plus the pulse)


def _pulse(scn: NodeScenario) -> np.ndarray:
    from mocknode.physics import hann_pulse

    acq, exc = scn.acquisition, scn.excitation
    n_pulse = math.ceil(exc.cycles / exc.frequency_hz * acq.fs_hz) + 1
    return hann_pulse(np.arange(n_pulse) / acq.fs_hz, exc.frequency_hz, exc.cycles)


def _geometry(scn: NodeScenario, velocity_m_s: float) -> dict:
    pipe = scn.pipe
    return dict(thickness_mm=pipe.wall_mm, mid_radius_mm=(pipe.outer_diameter_mm - pipe.wall_mm) / 2,
                shear_m_s=pipe.velocity_m_s, poisson=scn.modes.poisson_ratio,
                velocity_scale=velocity_m_s / pipe.velocity_m_s)


def _slowness_s_per_mm(kz: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Group delay per mm, d k_z / d omega, of the propagating bins (0 where evanescent)."""
    k = np.where(kz.imag == 0, kz.real, 0.0)
    grad = np.gradient(k, 2 * math.pi * f) if f.size > 1 else np.zeros_like(k)
    return np.where(kz.imag == 0, np.maximum(grad, 0.0), 0.0)


def _horizon_taper(delay_s: np.ndarray, horizon_s: float, ramp_s: float) -> np.ndarray:
    return np.clip((horizon_s - delay_s) / ramp_s, 0.0, 1.0)


def mode_traces(scn: NodeScenario, defects: list[ActiveDefect], velocity_m_s: float) -> np.ndarray | None:
    """The other modes' contribution [n_rx, n_samples] in the direct T(0,1) arrival's units (x direct_gain_v = volts).

    Transducer apertures: both rings filter a mode by sinc(k_z(f) h / 2 pi) (axial length h),
    normalised at the centre frequency to T(0,1)'s own filter, so a leak of ``amplitude`` a of a
    non-dispersive mode peaks at about a x the direct arrival (a conversion: ratio x |R_T|); the
    transducers' width and their cross-sensitivity to each mode are lumped into a and the ratio.

    None when the scenario has no leaks and no conversion applies (no defect present).
    ``velocity_m_s`` is T(0,1)'s at the current temperature; every bulk velocity scales with it.
    """
    spec = scn.modes
    if not spec.leaks and not (spec.conversions and defects):
        return None
    acq, rings, pipe = scn.acquisition, scn.rings, scn.pipe
    pulse = _pulse(scn)
    n_fft = sp_fft.next_fast_len(HORIZON_RECORDS * acq.n_samples + 2 * pulse.size, real=True)
    spectrum = sp_fft.rfft(pulse, n_fft)
    band = np.flatnonzero(np.abs(spectrum) > SPECTRUM_FLOOR * np.abs(spectrum).max())
    band = band[band > 0]
    f = sp_fft.rfftfreq(n_fft, 1.0 / acq.fs_hz)[band]
    pulse_s = pulse.size / acq.fs_hz
    record_end_s = acq.t0_s + acq.n_samples / acq.fs_hz
    horizon_s = acq.t0_s + n_fft / acq.fs_hz - pulse_s
    geometry = _geometry(scn, velocity_m_s)
    c_l_mm_s = bulk_velocities(velocity_m_s, spec.poisson_ratio)[0] * MM_PER_M
    c_t_mm_s = velocity_m_s * MM_PER_M
    near_end, far_end, refl = -rings.tx_axial_mm, pipe.length_mm - rings.tx_axial_mm, pipe.reflection_coefficient
    rx_theta = np.radians(np.asarray(rings.rx_angles))
    f0 = scn.excitation.frequency_hz
    t01_at_f0 = float(np.sinc(f0 * rings.transducer_length_mm / (pipe.velocity_m_s * MM_PER_M)))
    t0_shift = np.exp(2j * math.pi * f * acq.t0_s)
    h = rings.transducer_length_mm

    def outgoing(order: int, family: int, from_mm: float, max_delay_s: float):
        """Sum over the Rx ring's images of exp(-i k_z d), group delays tapered off at ``max_delay_s``;
        and one ring's axial aperture filter for the mode."""
        kz = axial_wavenumber(order, family, f, **geometry)
        slowness = _slowness_s_per_mm(kz, f)
        pos, amp = image_points(rings.tx_rx_distance_mm, near_end, far_end, refl,
                                max(record_end_s, 0.0) * c_l_mm_s, from_mm)
        dist = np.abs(pos - from_mm)
        phase = np.exp(-1j * kz[None, :] * dist[:, None])
        taper = _horizon_taper(dist[:, None] * slowness[None, :], max_delay_s, pulse_s)
        summed = np.sum(amp[:, None] * phase * taper, axis=0)
        # Aperture of one ring for this mode, relative to T(0,1)'s and to the mode's own at the centre
        # frequency: ``amplitude`` / ``ratio`` is what a receiver sees at f0; the band keeps the shape.
        kz0 = axial_wavenumber(order, family, np.array([f0]), **geometry)[0]
        at_f0 = np.sinc(kz0.real * h / (2 * math.pi))
        shape = np.sinc(kz.real * h / (2 * math.pi)) / at_f0 if abs(at_f0) > 1e-3 else np.ones_like(f)
        return summed, shape * t01_at_f0

    def to_time(spec_band: np.ndarray) -> np.ndarray:
        full = np.zeros(n_fft // 2 + 1, dtype=np.complex128)
        full[band] = spec_band * spectrum[band] * t0_shift
        return sp_fft.irfft(full, n_fft)[: acq.n_samples]

    total = np.zeros((len(rx_theta), acq.n_samples))
    for leak in spec.leaks:
        order, family = parse_mode(leak.mode)
        summed, axial = outgoing(order, family, 0.0, horizon_s)
        wave = to_time(summed * axial * axial * np.exp(1j * math.radians(leak.phase_deg)))
        pattern = np.cos(order * (rx_theta - math.radians(leak.angle_deg)))
        total += leak.amplitude * pattern[:, None] * wave[None, :]

    if spec.conversions and defects:
        lam, circ = wavelength_mm(scn), pipe.propagation_circumference_mm
        tx_aperture = np.sinc(f * h / c_t_mm_s)  # the incident wave is T(0,1)
        for defect in defects:
            z_in, a_in = image_points(0.0, near_end, far_end, refl, record_end_s * c_t_mm_s, defect.axial_mm)
            incident = np.sum(a_in[:, None] * np.exp(-2j * math.pi * f[None, :] * np.abs(defect.axial_mm - z_in)[:, None]
                                                     / c_t_mm_s), axis=0) * tx_aperture
            ring_reflection = defect.strength * lam / circ
            unit = defect.back / abs(defect.back) if abs(defect.back) > 0 else 1.0
            for conv in spec.conversions:
                order, family = parse_mode(conv.mode)
                summed, axial = outgoing(order, family, defect.axial_mm, horizon_s - max(record_end_s, 0.0))
                wave = to_time(incident * summed * axial * unit * np.exp(1j * math.radians(conv.phase_deg)))
                pattern = np.cos(order * (rx_theta - math.radians(defect.angle_deg)))
                total += conv.ratio * ring_reflection * pattern[:, None] * wave[None, :]
    return total
