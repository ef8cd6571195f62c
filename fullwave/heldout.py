"""Held-out full-wave cases: a seeded random draw of defects that neither benchmark set holds.

The dev set and the own cases (fullwave/cases.py) are fixed lists the imaging has been developed
against; accuracy is also judged on cases in neither. ``held_out_cases(seed, count)`` draws such
cases reproducibly: per case a ring (16 transducers at 85 kHz or 8 at 75 kHz), the ends, a defect
kind that ring is used for (notches of four sizes and a light mass on a 16-ring; near-rigid and
light masses and the paper's notch on an 8-ring), a position anywhere between 40 and 360 mm from
the Tx ring (the rings' near fields excluded) and round the whole pipe, and whether the records
are noisy; about one case in six is defect-free with a small temperature change, for false alarms.

The wave travels the record's circumference, pi x OD, as in the dev set (the own cases' mid-wall
wave needs ``wall_mm`` to be imaged right, which a node is configured with and the files lack), so
what the draw measures is the imaging, not a configuration. Names start with ``ho<seed>_``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from fullwave.cases import CASE_CELL_MM, DEEP_NOTCH, HEAVY, LIGHT, PAPER_NOTCH, SMALL_NOTCH, WIDE_NOTCH, Case
from fullwave.defects import Defect, Mass, Notch
from fullwave.record import PipeModel, SimulationSpec
from fullwave.transducers import RingLayout

SPAN_MM = (40.0, 360.0)  # a defect's axial position from the Tx ring (the Rx ring is 400 mm away)
DEFECT_FREE_SHARE = 1 / 6  # about this share of the cases has no defect
DEFECT_FREE_DT_C = 0.7  # ... and a temperature change within +- this
NOISY_SHARE = 0.5
MAX_COUNT = 500

# (transducers, excitation Hz) -> the defects such a ring is judged on: (label, kind, size)
RINGS: dict[tuple[int, float], tuple[tuple[str, type[Defect], dict], ...]] = {
    (16, 85e3): (("notch", Notch, PAPER_NOTCH), ("deep", Notch, DEEP_NOTCH), ("wide", Notch, WIDE_NOTCH),
                 ("small", Notch, SMALL_NOTCH), ("light", Mass, LIGHT)),
    (8, 75e3): (("mass", Mass, HEAVY), ("light", Mass, LIGHT), ("notch", Notch, PAPER_NOTCH)),
}


class HeldOutError(ValueError):
    """A draw that cannot be made (a negative seed, a count out of range)."""


def _spec(ends: str, n: int, frequency_hz: float) -> SimulationSpec:
    pipe = PipeModel(ends=ends)  # type: ignore[arg-type]
    pipe = dataclasses.replace(pipe, circumference_mm=math.pi * pipe.outer_diameter_mm)
    return SimulationSpec(pipe=pipe, rings=RingLayout(n_transducers=n), excitation_hz=frequency_hz,
                          cell_mm=CASE_CELL_MM)


def held_out_cases(seed: int, count: int) -> list[Case]:
    """``count`` cases drawn with ``seed`` (the same seed and count give the same cases; a larger
    count extends a smaller one's list)."""
    if seed < 0:
        raise HeldOutError(f"the seed must be >= 0, got {seed}")
    if not 1 <= count <= MAX_COUNT:
        raise HeldOutError(f"the count must be 1..{MAX_COUNT}, got {count}")
    rng = np.random.default_rng(seed)
    rings = list(RINGS)
    cases = []
    for k in range(count):
        n, frequency = rings[int(rng.integers(len(rings)))]
        ends = ("reflecting", "absorbing")[int(rng.integers(2))]
        noisy = bool(rng.random() < NOISY_SHARE)
        base = _spec(ends, n, frequency)
        stem = f"ho{seed}_{k:02d}_n{n}_{ends}"
        if rng.random() < DEFECT_FREE_SHARE:
            dt_c = round(float(rng.uniform(-DEFECT_FREE_DT_C, DEFECT_FREE_DT_C)), 2)
            current = base.with_changes(temperature_c=base.temperature_c + dt_c)
            name = f"{stem}_fa_{dt_c:+.2f}"
        else:
            label, kind, size = RINGS[(n, frequency)][int(rng.integers(len(RINGS[(n, frequency)])))]
            axial = float(round(rng.uniform(*SPAN_MM)))
            angle = float(round(rng.uniform(0.0, 360.0)) % 360)
            current = base.with_changes(defects=(kind(axial_mm=axial, angle_deg=angle, **size),))
            name = f"{stem}_{label}_{axial:.0f}_{angle:.0f}"
        cases.append(Case(f"{name}_noisy" if noisy else name, base, current, noisy))
    return cases


__all__ = ["HeldOutError", "held_out_cases"]
