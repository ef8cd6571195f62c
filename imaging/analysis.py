"""One baseline/current comparison end to end: DI map, defect estimate, the JSON summary."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from imaging.dimap import DIMap, compute_di_map
from imaging.grid import Grid
from imaging.localize import Estimate, locate_peak
from imaging.measurement import Measurement


@dataclass(frozen=True)
class Analysis:
    di_map: DIMap
    defects: list[Estimate]
    elapsed_ms: float
    extra: dict = field(default_factory=dict)

    @property
    def peak_di(self) -> float:
        return self.di_map.peak_di

    def as_json(self) -> dict:
        return {
            "peak_di": self.peak_di,
            "defects": [d.as_dict() for d in self.defects],
            "grid": self.di_map.grid.spec(),
            "method": self.di_map.method,
            "window_samples": self.di_map.window_samples,
            "elapsed_ms": self.elapsed_ms,
            **self.extra,
        }


def analyze(baseline: Measurement, current: Measurement, grid: Grid | None = None) -> Analysis:
    """Image ``current`` against ``baseline`` and estimate the defect position (strongest first)."""
    start = time.perf_counter()
    di_map = compute_di_map(baseline, current, grid)
    defects = [locate_peak(di_map)]
    return Analysis(di_map, defects, (time.perf_counter() - start) * 1e3)
