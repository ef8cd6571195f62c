"""How far a reported defect may be from where it is: a stated 90 % localization region.

A defect's position is the peak of its map; how sharply that peak is defined is the map's own
main lobe (the -3 dB widths, imaging/localize.py ``Confidence``), which the ring, the frequency
and the paths the record holds set: with reflecting ends the end paths cross the direct ones
and the lobe is a few mm long; without end echoes only the direct paths fix the axial position
and the lobe runs tens of mm along the axis. The region is a rectangle on the unrolled wall
centred on the estimate, its half-widths proportional to the lobe's half-widths, with a floor
(what the model's errors leave even under a sharp lobe: the transducers' and the defect's
finite size, the wave's mid-wall path):

    axial_half = max(AXIAL_FLOOR_MM, AXIAL_PER_LOBE x width_axial / 2)
    circumferential_half = max(CIRC_FLOOR_MM, CIRC_PER_LOBE x width_angle / 2 (as arc))

The factors are calibrated, not derived: over the full-wave dev set and the project's own
full-wave cases the truth lies inside the region for at least 90 % of the detected defects
(bench/bench_fullwave.py prints the hit rate and median size; docs/accuracy.md).

A map whose best competing peak is nearly as high as the estimate's (``peak_ratio`` >=
UNLOCALIZED_PEAK_RATIO), or whose lobe spans most of the imaged length, does not say where the
defect is, only that something changed: the region is then ``localized`` False, with the reason,
and its axial half-width covers the whole imaged length (a strong scatterer seen by a sparse
ring, full-wave: a near-rigid point mass on an 8-transducer ring); with a competing peak the
circumferential half-width is half the circumference too.

A sparse ring's defect (imaging/paths.py ``sparse_ring``: the Tx ring launches its
circumferential order N, modelled element by element) has its angle from the few receivers round
the ring, and both the map and the echo fit lean towards the nearest receiver's line: full-wave
8-transducer records at 75 kHz with absorbing ends (held-out draws) put defects 11 to 17 deg off a
line within 0-5 deg of it, sharply (the fit's own minimum there), while those imaged near the middle
between two lines were within 5 mm of arc but one (7.6). End echoes cross the direct paths and pin
the angle in part: with free ends the largest such lean was 10 deg (a 1 kg mass reported on a line,
9.8 mm of arc off). An estimate near a line may so have been drawn from much of the half pitch
either side; the region holds it (``receiver_lean_mm``, with ``receiver_lean``'s factor):

    circumferential_half >= CIRC_FLOOR_MM + lean x (arc from the estimate to the middle between
                            the two receivers' lines either side of it)
    lean = RECEIVER_LEAN (0.6) without end echoes (both ends' fitted reflection below
           LEAN_END_REFLECTION), RECEIVER_LEAN_WITH_ENDS (0.3) with them; 0 on a dense ring.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imaging.localize import Confidence
from imaging.paths import PathModel

COVERAGE = 0.9  # the region's stated probability of holding the truth
AXIAL_FLOOR_MM = 6.0
CIRC_FLOOR_MM = 6.0
AXIAL_PER_LOBE = 0.5
CIRC_PER_LOBE = 0.5
UNLOCALIZED_PEAK_RATIO = 0.95  # a competing peak this close to the estimate's: the position is not resolved
UNLOCALIZED_LOBE_FRACTION = 0.6  # ... nor when the lobe covers this much of the imaged axial length
RECEIVER_LEAN = 0.6  # of the arc to the middle between two receivers' lines a sparse ring's estimate may lean
RECEIVER_LEAN_WITH_ENDS = 0.3  # ... where an end echoes back (a fitted reflection of LEAN_END_REFLECTION or more)
LEAN_END_REFLECTION = 0.3  # a sparse ring's fit gives absorbing ends 0.1 (not 0), free ones 0.55


@dataclass(frozen=True)
class Region:
    """A ``coverage`` localization region: |axial error| <= ``axial_half_mm`` and |arc error| <=
    ``circumferential_half_mm`` (on the wall, wrap-aware). ``localized`` False: the map does not
    resolve the position (``reason``), the region is as wide as the evidence."""

    axial_half_mm: float
    circumferential_half_mm: float
    localized: bool = True
    reason: str | None = None
    coverage: float = COVERAGE

    def contains(self, axial_mm: float, angle_deg: float, true_axial_mm: float, true_angle_deg: float,
                 circumference_mm: float) -> bool:
        """True when the point (``true_axial_mm``, ``true_angle_deg``) lies in the region round the estimate."""
        diff = (true_angle_deg - angle_deg) % 360.0
        arc = min(diff, 360.0 - diff) * circumference_mm / 360.0
        return abs(true_axial_mm - axial_mm) <= self.axial_half_mm and arc <= self.circumferential_half_mm

    def holding(self, axial_offset_mm: float, arc_offset_mm: float) -> Region:
        """This region widened, where needed, to hold a second estimate at these offsets from the
        estimate with the floors' margin round it (AXIAL_FLOOR_MM, CIRC_FLOOR_MM). A defect placed by
        its echoes (imaging/multidefect.py ``echo_placed``) keeps its map's peak inside its region:
        which of the two is nearer the truth depends on the defect's kind (full-wave 16-ring notches
        without end echoes: the echoes; light masses: the map), which the record does not tell; and so
        the places along its line where its echoes fit nearly as well (``Found.axial_rivals_mm``)."""
        return dataclasses.replace(
            self, axial_half_mm=max(self.axial_half_mm, abs(axial_offset_mm) + AXIAL_FLOOR_MM),
            circumferential_half_mm=max(self.circumferential_half_mm, abs(arc_offset_mm) + CIRC_FLOOR_MM))

    def round_at_least(self, half_mm: float, circumference_mm: float) -> Region:
        """This region with a circumferential half-width of at least ``half_mm`` (at most half the
        circumference)."""
        half = min(max(self.circumferential_half_mm, half_mm), circumference_mm / 2.0)
        return dataclasses.replace(self, circumferential_half_mm=half)

    def as_dict(self) -> dict:
        return {
            "coverage": self.coverage,
            "axial_half_mm": round(self.axial_half_mm, 1),
            "circumferential_half_mm": round(self.circumferential_half_mm, 1),
            "localized": self.localized,
            "reason": self.reason,
        }


def localization_region(confidence: Confidence, *, circumference_mm: float, axial_span_mm: float) -> Region:
    """The 90 % region of an estimate whose map peak has ``confidence`` (see the module docstring).

    ``axial_span_mm``: the length the map images along the axis (the Tx-Rx distance)."""
    lobe_arc_mm = confidence.width_angle_deg * circumference_mm / 360.0
    axial = max(AXIAL_FLOOR_MM, AXIAL_PER_LOBE * confidence.width_axial_mm / 2.0)
    circ = min(max(CIRC_FLOOR_MM, CIRC_PER_LOBE * lobe_arc_mm / 2.0), circumference_mm / 2.0)
    if not math.isfinite(confidence.peak_ratio) or confidence.peak_ratio >= UNLOCALIZED_PEAK_RATIO:
        # A competing peak as high as this one, anywhere: neither coordinate is resolved.
        return Region(max(axial, axial_span_mm), circumference_mm / 2.0, False,
                      f"a competing peak at {confidence.peak_ratio:.0%} of this one's DI: the map does not resolve "
                      "where the change is")
    if confidence.width_axial_mm >= UNLOCALIZED_LOBE_FRACTION * axial_span_mm:
        # One lobe, long along the axis: the angle is known, the axial position is not.
        return Region(max(axial, axial_span_mm), circ, False,
                      f"the map's peak is {confidence.width_axial_mm:.0f} mm long along the axis: the axial "
                      "position is not resolved")
    return Region(axial, circ)


def receiver_lean(model: PathModel) -> float:
    """How far a defect imaged with ``model`` may lean to a receiver's line, as a fraction of the arc
    to the middle between two lines (module docstring): 0 for a dense ring's plane wave; for a sparse
    ring's (modelled by its elements, imaging/paths.py) RECEIVER_LEAN, or RECEIVER_LEAN_WITH_ENDS where
    an end echoes back LEAN_END_REFLECTION or more (imaging/ring_fit.py fits absorbing ends 0.1, not 0)."""
    if not model.elements:
        return 0.0
    ends = [r for end, r in ((model.near_end_mm, model.near_reflection), (model.far_end_mm, model.far_reflection))
            if end is not None]
    return RECEIVER_LEAN_WITH_ENDS if any(r >= LEAN_END_REFLECTION for r in ends) else RECEIVER_LEAN


def receiver_lean_mm(angle_deg: float, rx_angles_deg: Sequence[float], circumference_mm: float,
                     lean: float = RECEIVER_LEAN) -> float:
    """The circumferential half-width (mm) that holds a sparse ring's defect imaged at ``angle_deg``
    (module docstring): CIRC_FLOOR_MM + ``lean`` x the arc from it to the middle between the
    receivers' lines (``rx_angles_deg``, those imaged) on either side of it. One receiver: the middle
    is the opposite side."""
    lines = np.sort(np.asarray(rx_angles_deg, dtype=np.float64) % 360.0)
    if lines.size == 0:
        raise ValueError("no receiver: the lean has no line")
    gaps = np.diff(np.append(lines, lines[0] + 360.0))
    middles = lines + gaps / 2.0
    to_middle = float(np.min(np.abs((angle_deg - middles + 180.0) % 360.0 - 180.0)))
    return CIRC_FLOOR_MM + lean * to_middle * circumference_mm / 360.0


__all__ = ["COVERAGE", "Region", "localization_region", "receiver_lean", "receiver_lean_mm"]
