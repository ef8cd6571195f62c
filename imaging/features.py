"""Per-receiver damage features of the residual (baseline - current), as time series to image.

``feature[m, k]`` is the evidence for a scattered burst *starting* at sample k on receiver m,
normalised to the baseline's direct arrival so it is unit-free:

- ``"squared"`` — the paper's: sum of residual**2 over the W samples from k, divided by the
  direct arrival's energy over the same window (fraction of the direct arrival's energy);
- ``"envelope"`` — Hilbert envelope of the residual matched-filtered with the excitation
  burst, divided by the direct arrival's (fraction of the direct arrival's amplitude);
- ``"analytic"`` — the complex analytic signal whose modulus is the envelope: keeps the
  carrier phase, for imaging coherently within a path family.

The real features have their noise floor removed (see ``remove_noise_floor``), so noise alone images to
a map centred on zero rather than to a positive plateau.
"""
from __future__ import annotations

from typing import Literal

import numpy as np

from imaging.arrivals import analytic_matched, burst_autocorrelation_peak, hann_burst, matched_envelope
from imaging.dimap import windowed_energy
from imaging.scene import Scene

Feature = Literal["envelope", "squared", "analytic"]
FEATURES: tuple[str, ...] = ("envelope", "squared", "analytic")

# Rayleigh envelope of Gaussian noise: mean / lower quartile = sqrt(pi/2) / sqrt(-2 ln 0.75).
RAYLEIGH_MEAN_PER_Q25 = float(np.sqrt(np.pi / 2) / np.sqrt(-2 * np.log(0.75)))


class FeatureError(ValueError):
    """Unknown feature name or bad parameters."""


def remove_noise_floor(feature: np.ndarray, kind: str) -> np.ndarray:
    """Subtract each receiver's noise floor, estimated robustly from the quiet part of the record.

    Echoes occupy a minority of the record, so the lower quartile is noise: for an envelope
    (Rayleigh) the mean is 1.65 x the lower quartile; for windowed energy (chi-square with
    ~W degrees of freedom, nearly Gaussian) the median is used.
    """
    if kind == "envelope":
        floor = RAYLEIGH_MEAN_PER_Q25 * np.quantile(feature, 0.25, axis=-1, keepdims=True)
    else:
        floor = np.median(feature, axis=-1, keepdims=True)
    return feature - floor


def residual_feature(residual: np.ndarray, scene: Scene, *, floor: bool = True) -> np.ndarray:
    """The normalised feature [n_rx, n_samples] of a residual [n_rx, n_samples] (float64; complex128 for
    analytic): ``scene.feature`` at the scene's sampling and excitation, in units of its reference amplitude."""
    residual = np.asarray(residual, dtype=np.float64)
    fs_hz, excitation_hz, cycles, feature = scene.fs_hz, scene.excitation_hz, scene.cycles, scene.feature
    if feature == "envelope":
        scale = burst_autocorrelation_peak(fs_hz, excitation_hz, cycles) * scene.reference_amplitude_v
        out = matched_envelope(residual, fs_hz, excitation_hz, cycles) / scale
    elif feature == "analytic":
        scale = burst_autocorrelation_peak(fs_hz, excitation_hz, cycles) * scene.reference_amplitude_v
        burst = hann_burst(fs_hz, excitation_hz, cycles)
        return analytic_matched(residual, burst) / scale
    elif feature == "squared":
        burst = hann_burst(fs_hz, excitation_hz, cycles)
        w = int(scene.window_samples or burst.size)
        scale = float(np.sum(np.square(burst[:w]))) * scene.reference_amplitude_v**2
        out = windowed_energy(residual, w, 0, residual.shape[-1]) / scale
    else:
        raise FeatureError(f"unknown feature {feature!r}; choose one of {', '.join(FEATURES)}")
    return remove_noise_floor(out, feature) if floor else out
