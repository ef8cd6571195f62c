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
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from imaging.localize import Confidence

COVERAGE = 0.9  # the region's stated probability of holding the truth
AXIAL_FLOOR_MM = 6.0
CIRC_FLOOR_MM = 6.0
AXIAL_PER_LOBE = 0.5
CIRC_PER_LOBE = 0.5
UNLOCALIZED_PEAK_RATIO = 0.95  # a competing peak this close to the estimate's: the position is not resolved
UNLOCALIZED_LOBE_FRACTION = 0.6  # ... nor when the lobe covers this much of the imaged axial length


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


__all__ = ["COVERAGE", "Region", "localization_region"]
