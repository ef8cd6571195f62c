"""A node whose pipe is a pair of precomputed full-wave records (scenario ``fullwave``; docs/fullwave.md).

The records replace the ray physics (mocknode/physics.py) only: the baseline record is the pipe
before ``defect_appears_at_s``, the current record after it, and every acquisition passes the
record through the node's own receiver chain, exactly as ``physics.acquire`` passes its
simulated volts (receiver faults, noise of ``noise_v_rms / sqrt(averaging)`` drawn afresh, the
ADC). The records must describe the scenario's node: its rings, sampling and excitation; a
record that does not is refused when the node is set up, naming what differs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imaging.formats import load_measurement
from imaging.measurement import Measurement
from mocknode.physics import Acquisition, apply_receiver_faults, quantise_volts
from mocknode.scenario import NodeScenario

ANGLE_TOLERANCE_DEG = 1e-6


class RecordError(ValueError):
    """Full-wave records that cannot be served for this node (unreadable, or another node's)."""


@dataclass(frozen=True)
class RecordedPipe:
    """The two records of a node's pipe and when the current one takes over."""

    baseline: Measurement
    current: Measurement
    appears_at_s: float

    def record_at(self, elapsed_s: float) -> Measurement:
        return self.current if elapsed_s >= self.appears_at_s else self.baseline

    @property
    def n_samples(self) -> int:
        return self.baseline.n_samples


def _mismatch(name: str, record: Measurement, scn: NodeScenario) -> str | None:
    rings, acq, exc, pipe = scn.rings, scn.acquisition, scn.excitation, scn.pipe
    checks: list[tuple[str, bool]] = [
        ("receivers", record.n_rx == len(rings.rx_angles)
         and np.allclose(record.rx_angles_deg, rings.rx_angles, atol=ANGLE_TOLERANCE_DEG)),
        ("transmitters", record.tx_angles_deg.size == len(rings.tx_angles)
         and np.allclose(record.tx_angles_deg, rings.tx_angles, atol=ANGLE_TOLERANCE_DEG)),
        ("tx_rx_distance_mm", math.isclose(record.tx_rx_distance_mm, rings.tx_rx_distance_mm)),
        ("fs_hz", math.isclose(record.fs_hz, acq.fs_hz)),
        ("t0_s", math.isclose(record.t0_s, acq.t0_s, abs_tol=1e-12)),
        ("n_samples", record.n_samples >= acq.n_samples),
        ("excitation_hz", math.isclose(record.excitation_hz, exc.frequency_hz)),
        ("cycles", record.cycles == exc.cycles),
        ("pipe_length_mm", record.pipe_length_mm is None or math.isclose(record.pipe_length_mm, pipe.length_mm)),
        ("tx_axial_mm", record.tx_axial_mm is None or math.isclose(record.tx_axial_mm, rings.tx_axial_mm)),
    ]
    wrong = [key for key, ok in checks if not ok]
    return f"{name} record does not match the scenario's {', '.join(wrong)}" if wrong else None


def load_recorded_pipe(scn: NodeScenario) -> RecordedPipe:
    """Read and check the scenario's full-wave records (the node's only file I/O, at set-up)."""
    spec = scn.fullwave
    if spec is None:
        raise RecordError(f"{scn.node_id}: the scenario names no full-wave records")
    records = {}
    for name, path in (("baseline", spec.baseline), ("current", spec.current)):
        try:
            records[name] = load_measurement(path)
        except ValueError as exc:
            raise RecordError(f"{scn.node_id}: full-wave {name}: {exc}") from exc
        problem = _mismatch(name, records[name], scn)
        if problem:
            raise RecordError(f"{scn.node_id}: {problem} ({path})")
    return RecordedPipe(records["baseline"], records["current"], spec.defect_appears_at_s)


def acquire_recorded(scn: NodeScenario, pipe: RecordedPipe, elapsed_s: float,
                     rng: np.random.Generator) -> Acquisition:
    """One acquisition at ``elapsed_s``: the record of that time through the node's receiver chain."""
    record = pipe.record_at(elapsed_s)
    acq = scn.acquisition
    volts = apply_receiver_faults(record.traces[:, : acq.n_samples].astype(np.float64), scn, elapsed_s)
    if acq.noise_v_rms > 0:
        volts = volts + rng.standard_normal(volts.shape) * (acq.noise_v_rms / math.sqrt(acq.averaging))
    codes, volts_per_code = quantise_volts(volts, acq.adc_bits, acq.adc_full_scale_v)
    return Acquisition(codes, volts_per_code, acq.fs_hz, acq.t0_s, record.temperature_c, elapsed_s)


__all__ = ["RecordError", "RecordedPipe", "acquire_recorded", "load_recorded_pipe"]
