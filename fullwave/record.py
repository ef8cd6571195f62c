"""One full-wave record: a simulation spec in, an ``imaging.measurement.Measurement`` out.

The record is what the node would store before its ADC: every receiver's output (volts, noise
free) sampled at ``fs_hz`` from the start of the excitation (``t0_s`` = 0), with the geometry
the node knows (``circumference_mm`` = pi x OD, the nominal T(0,1) velocity 3130 m/s) and
``pipe_length_mm`` / ``tx_axial_mm``. The wave itself travels on the mid-wall circumference
pi (OD - wall) unless ``circumference_mm`` says otherwise (the imaging sees the 3.5 % mismatch a
real pipe gives). Noise, ADC and decimation are fullwave/acquisition.py's.

Receiver samples come at the leapfrog's half steps; they are resampled onto the output clock by
a cubic spline (the signals are band-limited far below the simulation's sampling rate: error
~(2 pi f dt)^4 / 384, 4e-7 of the amplitude at 85 kHz and dt = 0.2 us).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.interpolate import CubicSpline

from fullwave import inplane, sh
from fullwave.absorber import cpml
from fullwave.defects import Defect, apply_defects
from fullwave.dispersion import stable_dt_s
from fullwave.grid import Grid, GridError, make_grid
from fullwave.medium import Medium, MediumError, Steel, modulus_scale, uniform_medium
from fullwave.transducers import RingLayout, TransducerError, plane_wave_velocity_m_s, tone_burst
from imaging.measurement import DEFAULT_VELOCITY_M_S, Measurement

TRACTION_PA = 1.0  # Tx traction amplitude; the system is linear, volts are set by the receivers' gain
DIRECT_ARRIVAL_V = 0.0825  # the paper's 16-transducer ring, far-field plane wave (paper, Table 3: 82.5 mV)
DEFAULT_ABSORBER_MM = 80.0  # absorbing layer beyond each absorbing end (~2 wavelengths at 75-85 kHz)


ENGINES = {"sh": sh, "inplane": inplane}


class SimulationError(ValueError):
    """A simulation spec that cannot be run (geometry, grid, material)."""


@dataclass(frozen=True)
class PipeModel:
    """The paper's pipe (Table 1) by default; ``ends`` as in the dev set's manifest."""

    outer_diameter_mm: float = 114.6
    wall_mm: float = 4.0
    length_mm: float = 1000.0
    ends: Literal["reflecting", "absorbing"] = "reflecting"
    steel: Steel = field(default_factory=Steel)
    circumference_mm: float | None = None  # modelled wall's circumference; None: mid-wall pi (OD - wall)
    absorber_mm: float = DEFAULT_ABSORBER_MM

    @property
    def wave_circumference_mm(self) -> float:
        if self.circumference_mm is not None:
            return self.circumference_mm
        return math.pi * (self.outer_diameter_mm - self.wall_mm)


@dataclass(frozen=True)
class SimulationSpec:
    """Everything one simulation depends on (its JSON form keys the cache)."""

    pipe: PipeModel = field(default_factory=PipeModel)
    rings: RingLayout = field(default_factory=RingLayout)
    excitation_hz: float = 85e3
    cycles: int = 5
    defects: tuple[Defect, ...] = ()
    temperature_c: float = 20.0
    reference_c: float = 20.0
    velocity_temp_coeff_per_c: float = -1e-4  # c(T) = c(T_ref) (1 + k (T - T_ref)); the dev set's value
    model: Literal["sh", "inplane"] = "sh"
    cell_mm: float = 1.0
    courant: float = 0.9
    fs_hz: float = 10e6
    n_samples: int = 6000

    def with_changes(self, **changes) -> SimulationSpec:
        return dataclasses.replace(self, **changes)


def build_grid(spec: SimulationSpec) -> Grid:
    pipe = spec.pipe
    absorber = pipe.absorber_mm if pipe.ends == "absorbing" else 0.0
    return make_grid(pipe.length_mm, pipe.wave_circumference_mm, spec.cell_mm, absorber)


def build_medium(spec: SimulationSpec, grid: Grid) -> Medium:
    pipe = spec.pipe
    factor = modulus_scale(spec.temperature_c, spec.reference_c, spec.velocity_temp_coeff_per_c)
    medium = uniform_medium(grid, pipe.wall_mm * 1e-3, pipe.steel, factor)
    return apply_defects(medium, spec.defects, spec.rings.tx_axial_mm, pipe.steel.density_kg_m3)


def receiver_gain_v_per_m_s(spec: SimulationSpec) -> float:
    """Volts per m/s of the receivers: the paper's 16-transducer ring's direct arrival at 82.5 mV
    (its far-field plane wave, filtered by the Tx and the Rx patch's axial length at the centre
    frequency, sinc^2(f l / c)), so a ring of fewer transducers gives proportionally less signal."""
    pipe = spec.pipe
    reference = RingLayout(n_transducers=16)
    c = pipe.steel.shear_velocity_m_s
    v = plane_wave_velocity_m_s(reference, pipe.wave_circumference_mm * 1e-3,
                                pipe.steel.density_kg_m3 * pipe.wall_mm * 1e-3, c, TRACTION_PA)
    aperture = np.sinc(spec.excitation_hz * reference.patch_axial_mm * 1e-3 / c) ** 2
    return DIRECT_ARRIVAL_V / (v * aperture)


def _validate(spec: SimulationSpec) -> None:
    if spec.rings.rx_axial_mm + spec.rings.patch_axial_mm / 2 > spec.pipe.length_mm:
        raise SimulationError("the Rx ring lies beyond the pipe's far end")
    if not (spec.fs_hz > 0 and spec.n_samples >= 2 and spec.excitation_hz > 0 and spec.cycles >= 1):
        raise SimulationError("fs_hz, n_samples, excitation_hz and cycles must be positive")
    if not 0 < spec.courant <= 1:
        raise SimulationError("courant must be in (0, 1]")
    if spec.pipe.ends not in ("reflecting", "absorbing"):
        raise SimulationError(f"ends must be 'reflecting' or 'absorbing', got {spec.pipe.ends!r}")


def simulate_velocities(spec: SimulationSpec, dtype: type = np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Receiver outputs before the gain: (times s [n_steps + 1], along-direction velocity m/s
    [n_steps + 1, n_rx]), starting with the quiet pipe at t = 0."""
    _validate(spec)
    if spec.model not in ENGINES:
        raise SimulationError(f"unknown model {spec.model!r}: one of {', '.join(ENGINES)}")
    engine = ENGINES[spec.model]
    try:
        grid = build_grid(spec)
        medium = build_medium(spec, grid)
        velocity = medium.max_velocity_m_s if spec.model == "inplane" else medium.max_shear_velocity_m_s
        dt = stable_dt_s(grid.dz_m, grid.ds_m, velocity, spec.courant)
        n_steps = math.ceil(spec.n_samples / spec.fs_hz / dt) + 4
        amplitude = TRACTION_PA * tone_burst(np.arange(n_steps) * dt, spec.excitation_hz, spec.cycles)
        out = engine.simulate(medium, dt, cpml(grid, velocity, spec.excitation_hz, dt), spec.rings, amplitude,
                              spec.rings.direction, dtype)
    except (GridError, MediumError, TransducerError) as exc:
        raise SimulationError(str(exc)) from exc
    times = np.concatenate([[0.0], (np.arange(n_steps) + 0.5) * dt])
    return times, np.vstack([np.zeros((1, out.shape[1])), out])


def resample(times_s: np.ndarray, samples: np.ndarray, fs_hz: float, n_samples: int) -> np.ndarray:
    """[n_rx, n_samples] at t = k / fs from samples [n_times, n_rx] at ``times_s`` (cubic spline)."""
    t_out = np.arange(n_samples) / fs_hz
    if t_out[-1] > times_s[-1]:
        raise SimulationError("the simulation ends before the record")
    return CubicSpline(times_s, samples, axis=0)(t_out).T


def simulate(spec: SimulationSpec, dtype: type = np.float32) -> Measurement:
    """The noise-free record (volts) of ``spec``."""
    times, velocity = simulate_velocities(spec, dtype)
    traces = resample(times, velocity, spec.fs_hz, spec.n_samples) * receiver_gain_v_per_m_s(spec)
    pipe, rings = spec.pipe, spec.rings
    return Measurement(
        traces=traces.astype(np.float32),
        fs_hz=spec.fs_hz,
        t0_s=0.0,
        rx_angles_deg=np.asarray(rings.rx_angles, dtype=np.float64),
        tx_angles_deg=np.asarray(rings.tx_angles, dtype=np.float64),
        tx_rx_distance_mm=rings.tx_rx_distance_mm,
        circumference_mm=math.pi * pipe.outer_diameter_mm,
        velocity_m_s=DEFAULT_VELOCITY_M_S,
        excitation_hz=spec.excitation_hz,
        cycles=spec.cycles,
        temperature_c=spec.temperature_c,
        pipe_length_mm=pipe.length_mm,
        tx_axial_mm=rings.tx_axial_mm,
    )


__all__ = ["DIRECT_ARRIVAL_V", "PipeModel", "SimulationError", "SimulationSpec", "build_grid", "build_medium",
           "receiver_gain_v_per_m_s", "resample", "simulate", "simulate_velocities"]
