"""Synthetic measurements for tests: a direct arrival, and a point scatterer's echo at a known position."""
from __future__ import annotations

import math

import numpy as np

from imaging.measurement import Measurement

OD_MM = 114.6
CIRCUMFERENCE_MM = math.pi * OD_MM
C_M_S = 3130.0


def hanning_pulse(t_s: np.ndarray, frequency_hz: float = 85e3, cycles: int = 5, lag_rad: float = 0.0) -> np.ndarray:
    """The paper's excitation: a Hanning-windowed sine burst, zero outside 0 <= t <= cycles/f; ``lag_rad``
    delays the carrier only (a scatterer's phase), not the envelope."""
    inside = (t_s >= 0) & (t_s <= cycles / frequency_hz)
    phase = 2 * np.pi * frequency_hz * t_s
    return np.where(inside, 0.5 * (1 - np.cos(phase / cycles)) * np.sin(phase - lag_rad), 0.0)


def measurement(traces: np.ndarray, rx_angles_deg: np.ndarray, **overrides) -> Measurement:
    fields = dict(
        traces=traces,
        fs_hz=10e6,
        t0_s=0.0,
        rx_angles_deg=rx_angles_deg,
        tx_angles_deg=rx_angles_deg,
        tx_rx_distance_mm=400.0,
        circumference_mm=CIRCUMFERENCE_MM,
        velocity_m_s=C_M_S,
        excitation_hz=85e3,
        cycles=5,
        temperature_c=20.0,
    )
    fields.update(overrides)
    return Measurement(**fields)


def baseline_and_scatterer(
    axial_mm: float,
    angle_deg: float,
    *,
    n_rx: int = 16,
    n_samples: int = 6000,
    amplitude: float = 0.05,
    noise_rms: float = 0.0,
    seed: int = 0,
) -> tuple[Measurement, Measurement]:
    """A baseline with the direct arrival, and the same plus the echo of a point scatterer.

    The scattered 5-cycle Hanning pulse reaches each receiver after travelling axially from
    the Tx ring to the scatterer, then along the shortest line on the unrolled wall.
    """
    rng = np.random.default_rng(seed)
    fs = 10e6
    t = np.arange(n_samples) / fs
    rx = np.arange(n_rx) * 360.0 / n_rx
    c_mm_s = C_M_S * 1000.0
    direct = hanning_pulse(t - 400.0 / c_mm_s)
    base = np.tile(direct, (n_rx, 1))
    diff = np.mod(angle_deg - rx, 360.0)
    arc = np.minimum(diff, 360.0 - diff) * CIRCUMFERENCE_MM / 360.0
    r = np.hypot(400.0 - axial_mm, arc)
    echo = np.stack([hanning_pulse(t - (axial_mm + r_m) / c_mm_s) for r_m in r])
    echo *= amplitude / np.sqrt(np.maximum(r, 10.0) / 37.0)[:, None]
    cur = base + echo
    if noise_rms:
        base = base + rng.normal(0, noise_rms, base.shape)
        cur = cur + rng.normal(0, noise_rms, cur.shape)
    return measurement(base.astype(np.float32), rx), measurement(cur.astype(np.float32), rx)


def baseline_and_scatterers(
    scatterers: list[tuple[float, float, float]],
    *,
    n_rx: int = 16,
    n_samples: int = 6000,
    noise_rms: float = 0.0,
    seed: int = 0,
    both_ways: bool = True,
    forward_lag_rad: float = 0.0,
    taper_power: float = 0.0,
) -> tuple[Measurement, Measurement]:
    """Like ``baseline_and_scatterer`` for several point scatterers (axial_mm, angle_deg, amplitude).

    With ``both_ways`` each echo also arrives the long way round the pipe, as a real scattered
    wave does. Amplitude falls as 1/sqrt(distance) (2-D spreading), as above. ``forward_lag_rad``
    (b) gives each echo a carrier phase lag b (1 - cos psi), psi its scattering angle (between the
    incident wave, +z, and the way to the receiver): a finite scatterer's phase pattern, such as a
    notch's (docs/accuracy.md), which on these direct paths equals a move of b / k along the axis.
    ``taper_power`` (p) scales each echo by cos(psi)^p: an amplitude pattern without a phase law
    (the mock node's mass radiates as cos^2 of the outgoing direction).
    """
    rng = np.random.default_rng(seed)
    fs = 10e6
    t = np.arange(n_samples) / fs
    rx = np.arange(n_rx) * 360.0 / n_rx
    c_mm_s = C_M_S * 1000.0
    base = np.tile(hanning_pulse(t - 400.0 / c_mm_s), (n_rx, 1))
    cur = base.copy()
    for axial_mm, angle_deg, amplitude in scatterers:
        diff = np.mod(angle_deg - rx, 360.0)
        short = np.minimum(diff, 360.0 - diff) * CIRCUMFERENCE_MM / 360.0
        legs = [short, CIRCUMFERENCE_MM - short] if both_ways else [short]
        for arc in legs:
            r = np.hypot(400.0 - axial_mm, arc)
            lag = forward_lag_rad * (1.0 - (400.0 - axial_mm) / np.maximum(r, 1e-9))
            for m in range(n_rx):
                pattern = ((400.0 - axial_mm) / max(r[m], 1e-9)) ** taper_power
                cur[m] += amplitude * pattern / np.sqrt(max(r[m], 10.0) / 37.0) * hanning_pulse(
                    t - (axial_mm + r[m]) / c_mm_s, lag_rad=float(lag[m]))
    if noise_rms:
        base = base + rng.normal(0, noise_rms, base.shape)
        cur = cur + rng.normal(0, noise_rms, cur.shape)
    return measurement(base.astype(np.float32), rx), measurement(cur.astype(np.float32), rx)


def mock_pipe_record(temperature_c: float, seed: int) -> Measurement:
    """One record of the mock node's physics (paper pipe, reflecting ends, default noise) at a steady
    pipe temperature: what temperature does to a sound pipe, compensation included."""
    from mocknode.physics import acquire
    from mocknode.scenario import NodeScenario, TemperatureSpec

    scn = NodeScenario(node_id="t", temperature=TemperatureSpec(mean_c=temperature_c, daily_amplitude_c=0.0))
    return acquire(scn, 0.0, np.random.default_rng(seed)).to_measurement(scn)
