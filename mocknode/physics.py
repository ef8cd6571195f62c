"""Receiver traces of a simulated node: analytic T(0,1) arrivals superposed as delayed, scaled pulses.

Pure functions of a NodeScenario, an elapsed time, a temperature and a numpy Generator. Every
arrival (direct, end reflections, defect scattering along every path) is computed in
mocknode/paths.py; here they are rendered in the frequency domain (exact fractional delays,
constant phase shifts, receiver-aperture filters), then noise, ADC and decimation are applied.
Other guided modes (ring leakage, mode conversion at defects; opt-in) come from mocknode/modes.py.
Model and assumptions: docs/simulator.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import fft as sp_fft

from imaging.measurement import Measurement
from mocknode.modes import mode_traces
from mocknode.paths import Arrivals, direct_arrivals, scattered_arrivals
from mocknode.scattering import MM_PER_M, ActiveDefect, defects_at, wavelength_mm
from mocknode.scenario import NodeScenario

SPECTRUM_FLOOR = 1e-5  # pulse spectrum bins below this fraction of the peak are not synthesised


class PhysicsError(ValueError):
    """Arguments to the simulator are out of range (e.g. a bad decimation factor)."""


def hann_pulse(t_s: np.ndarray, frequency_hz: float, cycles: int) -> np.ndarray:
    """H(t) = 0.5 (1 - cos(2 pi f t / n)) sin(2 pi f t) for 0 <= t <= n/f, zero elsewhere (unit peak ~1)."""
    t = np.asarray(t_s, dtype=np.float64)
    phase = 2 * math.pi * frequency_hz * t
    inside = (t >= 0) & (t <= cycles / frequency_hz)
    return np.where(inside, 0.5 * (1 - np.cos(phase / cycles)) * np.sin(phase), 0.0)


def velocity_m_s(scn: NodeScenario, temperature_c: float) -> float:
    """T(0,1) group velocity at a temperature: c0 (1 - k (T - T_ref))."""
    pipe = scn.pipe
    return pipe.velocity_m_s * (1.0 - pipe.velocity_temp_coeff_per_c * (temperature_c - scn.temperature.reference_c))


def temperature_at(scn: NodeScenario, elapsed_s: float, rng: np.random.Generator) -> float:
    """Pipe temperature (degC): mean + daily sine (zero at elapsed 0) + Gaussian jitter per measurement."""
    spec = scn.temperature
    daily = spec.daily_amplitude_c * math.sin(2 * math.pi * elapsed_s / spec.period_s)
    jitter = spec.jitter_c * float(rng.standard_normal()) if spec.jitter_c > 0 else 0.0
    return spec.mean_c + daily + jitter


def all_arrivals(scn: NodeScenario, defects: list[ActiveDefect], velocity: float) -> Arrivals:
    """Direct and end-reflected waves plus every defect's scattered paths that start within the record."""
    acq, rings, pipe = scn.acquisition, scn.rings, scn.pipe
    record_end_s = acq.t0_s + acq.n_samples / acq.fs_hz
    max_path_mm = max(record_end_s, 0.0) * velocity * MM_PER_M
    near_end, far_end = -rings.tx_axial_mm, pipe.length_mm - rings.tx_axial_mm
    circ = pipe.propagation_circumference_mm
    rx_s = np.asarray(rings.rx_angles) / 360.0 * circ
    parts = [direct_arrivals(rx_s.size, rings.tx_rx_distance_mm, near_end, far_end,
                             pipe.reflection_coefficient, max_path_mm)]
    lam = wavelength_mm(scn)
    parts += [scattered_arrivals(d, rx_s, rings.tx_rx_distance_mm, near_end, far_end, pipe.reflection_coefficient,
                                 circ, lam, max_path_mm) for d in defects]
    return Arrivals.concat(parts)


def _pulse_band(scn: NodeScenario, n_fft: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bin indices, frequencies Hz, spectrum) of the sampled excitation pulse where it is significant."""
    acq, exc = scn.acquisition, scn.excitation
    n_pulse = math.ceil(exc.cycles / exc.frequency_hz * acq.fs_hz) + 1
    pulse = hann_pulse(np.arange(n_pulse) / acq.fs_hz, exc.frequency_hz, exc.cycles)
    spectrum = sp_fft.rfft(pulse, n_fft)
    freqs = sp_fft.rfftfreq(n_fft, 1.0 / acq.fs_hz)
    idx = np.flatnonzero(np.abs(spectrum) > SPECTRUM_FLOOR * np.abs(spectrum).max())
    return idx, freqs[idx], spectrum[idx]


def _fft_length(scn: NodeScenario) -> int:
    acq, exc = scn.acquisition, scn.excitation
    n_pulse = math.ceil(exc.cycles / exc.frequency_hz * acq.fs_hz) + 1
    # Room for a pulse hanging off either end of the record, so circular wrap never shows.
    return sp_fft.next_fast_len(acq.n_samples + 2 * n_pulse + 2, real=True)


def render(scn: NodeScenario, arrivals: Arrivals, velocity: float) -> np.ndarray:
    """Sum of pulses H(t - path/c) * amplitude, filtered by the transducer apertures; [n_rx, n_samples].

    A transducer of length h (axial) and width w integrates the wave over its face: for a
    locally plane wave arriving at angle a from the axis that is a boxcar in time of duration
    (h |cos a| + ...)/c, i.e. sinc(f h |cos a| / c) * sinc(f w |sin a| / c) in frequency.
    Units: the incident plane wave has unit amplitude before the aperture filters.
    """
    acq, rings = scn.acquisition, scn.rings
    n_fft = _fft_length(scn)
    idx, f, spectrum = _pulse_band(scn, n_fft)
    c_mm_s = velocity * MM_PER_M
    shift_s = arrivals.path_mm / c_mm_s - acq.t0_s
    n_pulse_s = scn.excitation.cycles / scn.excitation.frequency_hz
    in_record = (shift_s <= acq.n_samples / acq.fs_hz) & (shift_s >= -n_pulse_s)
    amp = np.where(in_record, arrivals.amplitude, 0.0)
    tx_aperture = np.sinc(f * rings.transducer_length_mm / c_mm_s)  # Tx ring launches a plane wave
    rx_len = np.sinc(f[None, None, :] * (rings.transducer_length_mm * np.abs(arrivals.cos_arrival))[..., None] / c_mm_s)
    rx_wid = np.sinc(f[None, None, :] * (rings.transducer_width_mm * np.abs(arrivals.sin_arrival))[..., None] / c_mm_s)
    phasor = np.exp(-2j * math.pi * f[None, None, :] * shift_s[..., None])
    summed = np.einsum("rp,rpf->rf", amp, phasor * rx_len * rx_wid)
    full = np.zeros((arrivals.path_mm.shape[0], n_fft // 2 + 1), dtype=np.complex128)
    full[:, idx] = summed * (spectrum * tx_aperture)[None, :]
    return sp_fft.irfft(full, n_fft, axis=-1)[:, : acq.n_samples]


def direct_gain_v(scn: NodeScenario) -> float:
    """Volts per unit wave amplitude, chosen so the direct arrival peaks at acquisition.direct_amplitude_v."""
    n_fft = _fft_length(scn)
    idx, f, spectrum = _pulse_band(scn, n_fft)
    c_mm_s = scn.pipe.velocity_m_s * MM_PER_M
    aperture = np.sinc(f * scn.rings.transducer_length_mm / c_mm_s) ** 2
    full = np.zeros(n_fft // 2 + 1, dtype=np.complex128)
    full[idx] = spectrum * aperture
    return scn.acquisition.direct_amplitude_v / float(np.abs(sp_fft.irfft(full, n_fft)).max())


def simulate_volts(scn: NodeScenario, *, elapsed_s: float, temperature_c: float,
                   rng: np.random.Generator, include_noise: bool = True) -> np.ndarray:
    """Averaged receiver voltages, float64 [n_rx, n_samples], before the ADC.

    Noise is white Gaussian with noise_v_rms per shot, divided by sqrt(averaging).
    """
    velocity = velocity_m_s(scn, temperature_c)
    if not (math.isfinite(velocity) and velocity > 0):
        raise PhysicsError(f"temperature {temperature_c} degC gives a non-physical velocity {velocity} m/s")
    defects = defects_at(scn, elapsed_s)
    waves = render(scn, arrivals=all_arrivals(scn, defects, velocity), velocity=velocity)
    other_modes = mode_traces(scn, defects, velocity) if scn.modes.active else None
    if other_modes is not None:
        waves = waves + other_modes
    volts = apply_receiver_faults(waves * direct_gain_v(scn), scn, elapsed_s)
    acq = scn.acquisition
    if include_noise and acq.noise_v_rms > 0:
        volts = volts + rng.standard_normal(volts.shape) * (acq.noise_v_rms / math.sqrt(acq.averaging))
    return volts


def apply_receiver_faults(volts: np.ndarray, scn: NodeScenario, elapsed_s: float) -> np.ndarray:
    """The noise-free receiver signals with the scenario's receiver faults active at ``elapsed_s``:
    each faulty row delayed by ``delay_s`` (linear interpolation, zero before the record) and scaled
    by ``gain``. Returns ``volts`` itself when no fault is active."""
    active = [f for f in scn.receiver_faults if f.active_at(elapsed_s)]
    if not active:
        return volts
    out = volts.copy()
    t = np.arange(volts.shape[1]) / scn.acquisition.fs_hz
    for fault in active:
        row = out[fault.rx_index]
        if fault.delay_s:
            row = np.interp(t - fault.delay_s, t, row, left=0.0, right=0.0)
        out[fault.rx_index] = row * fault.gain
    return out


def quantise_volts(volts: np.ndarray, adc_bits: int, full_scale_v: float) -> tuple[np.ndarray, float]:
    """Signed ADC codes (int16, clipped to [-2^(b-1), 2^(b-1)-1]) and the volts per code."""
    if not 2 <= adc_bits <= 16:
        raise PhysicsError(f"adc_bits must be 2..16, got {adc_bits}")
    half = 2 ** (adc_bits - 1)
    volts_per_code = full_scale_v / half
    codes = np.clip(np.rint(np.asarray(volts) / volts_per_code), -half, half - 1)
    return codes.astype(np.int16), volts_per_code


def decimate_codes(codes: np.ndarray, factor: int, *, axis: int = -1,
                   method: Literal["subsample", "boxcar"] = "subsample") -> np.ndarray:
    """What the FPGA keeps for its on-board DI map: every ``factor``-th sample along ``axis``.

    The paper only says "decimated by 10X"; we model the cheapest FPGA choice, a plain
    subsample starting at sample 0 (no anti-alias filter: at 10 MHz -> 1 MHz the 75-85 kHz
    pulse is far below the new Nyquist, but the white noise folds in unreduced).
    ``method="boxcar"`` averages each block of ``factor`` samples instead (noise / sqrt(factor),
    a delay of (factor-1)/2 samples and a slight high-frequency droop). Output length is
    ceil(n / factor) either way; dtype is int16.
    """
    if not isinstance(factor, (int, np.integer)) or factor < 1:
        raise PhysicsError(f"decimation factor must be a positive integer, got {factor!r}")
    codes = np.asarray(codes)
    moved = np.moveaxis(codes, axis, -1)
    n = moved.shape[-1]
    if method == "subsample":
        out = moved[..., ::factor]
    elif method == "boxcar":
        n_blocks = -(-n // factor)
        padded = np.full(moved.shape[:-1] + (n_blocks * factor,), np.nan)
        padded[..., :n] = moved
        out = np.rint(np.nanmean(padded.reshape(moved.shape[:-1] + (n_blocks, factor)), axis=-1))
    else:
        raise PhysicsError(f"unknown decimation method {method!r}")
    return np.moveaxis(out.astype(np.int16), -1, axis)


@dataclass(frozen=True)
class Acquisition:
    """One averaged acquisition as the node stores it: ADC codes [n_rx, n_samples] and their scale."""

    codes: np.ndarray
    volts_per_code: float
    fs_hz: float
    t0_s: float
    temperature_c: float
    elapsed_s: float

    def to_measurement(self, scn: NodeScenario) -> Measurement:
        """The interchange record; velocity is the nominal one (the node does not know the true c(T))."""
        rings, pipe, exc = scn.rings, scn.pipe, scn.excitation
        return Measurement(
            traces=(self.codes.astype(np.float32) * np.float32(self.volts_per_code)),
            fs_hz=self.fs_hz,
            t0_s=self.t0_s,
            rx_angles_deg=np.asarray(rings.rx_angles),
            tx_angles_deg=np.asarray(rings.tx_angles),
            tx_rx_distance_mm=rings.tx_rx_distance_mm,
            circumference_mm=pipe.outer_circumference_mm,
            velocity_m_s=pipe.velocity_m_s,
            excitation_hz=exc.frequency_hz,
            cycles=exc.cycles,
            temperature_c=self.temperature_c,
            pipe_length_mm=pipe.length_mm,
            tx_axial_mm=rings.tx_axial_mm,
            extra={"node_id": scn.node_id, "elapsed_s": self.elapsed_s, "volts_per_code": self.volts_per_code},
        )


def acquire(scn: NodeScenario, elapsed_s: float, rng: np.random.Generator) -> Acquisition:
    """Simulate one measurement at ``elapsed_s``: temperature, traces, noise, ADC."""
    temperature = temperature_at(scn, elapsed_s, rng)
    volts = simulate_volts(scn, elapsed_s=elapsed_s, temperature_c=temperature, rng=rng)
    acq = scn.acquisition
    codes, volts_per_code = quantise_volts(volts, acq.adc_bits, acq.adc_full_scale_v)
    return Acquisition(codes, volts_per_code, acq.fs_hz, acq.t0_s, temperature, elapsed_s)


__all__ = [
    "Acquisition",
    "ActiveDefect",
    "PhysicsError",
    "acquire",
    "apply_receiver_faults",
    "decimate_codes",
    "defects_at",
    "hann_pulse",
    "quantise_volts",
    "simulate_volts",
    "temperature_at",
    "velocity_m_s",
]
