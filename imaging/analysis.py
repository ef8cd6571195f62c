"""One baseline/current comparison end to end: DI map, defect estimates, the JSON summary.

A thin front to ``imaging.pipeline.assess`` for callers holding one explicit baseline (the
CLI, the gateway): a library of one, never abstaining (the caller chose the baseline), on the
full 1 mm x 1 deg grid unless told otherwise.
"""
from __future__ import annotations

import math

from imaging.grid import Grid
from imaging.measurement import Measurement
from imaging.pipeline import Assessment, AssessSettings

Analysis = Assessment  # the result type; kept under its old name for existing callers


def analyze(
    baseline: Measurement,
    current: Measurement,
    grid: Grid | None = None,
    *,
    method: str = "multipath",
    feature: str = "analytic",
    threshold: float | None = None,
    max_defects: int = 3,
    compensate: bool = True,
    wall_mm: float | None = None,
    thermometer: bool = True,
) -> Assessment:
    """Image ``current`` against ``baseline`` (default: the all-paths coherent method) and find defects.

    ``defects`` lists only what crosses the detection threshold (strongest first); ``peak`` and
    ``peak_di`` are always there. A sparse Tx ring (imaging/paths.py ``sparse_ring``) is mapped on
    the gateway's coarse grid unless ``grid`` is given. ``method="paper"`` is Algorithm 1 (DI normalised by the
    direct arrival's own window energy).
    """
    from imaging.dimap import check_compatible
    from imaging.multipath import path_model_for
    from imaging.pipeline import assess, default_grid

    check_compatible(baseline, current)  # one explicit baseline: a mismatch is the caller's error
    if grid is None and method == "multipath" and path_model_for(baseline, wall_mm=wall_mm).elements:
        # A sparse Tx ring's element-by-element model has ~50x the paths: its gather tables on the
        # 1 mm x 1 deg grid would take GBs. The coarse grid, with every peak refined at 1 mm x 1 deg.
        grid = default_grid(method, current.tx_rx_distance_mm, current.rx_angles_deg)
    settings = AssessSettings(
        method=method,  # type: ignore[arg-type]
        feature=feature,  # type: ignore[arg-type]
        compensate=compensate,
        thermometer=thermometer,
        max_residual=math.inf,
        threshold=threshold,
        max_defects=max_defects,
        grid=grid or Grid.default(current.tx_rx_distance_mm),
        wall_mm=wall_mm,
    )
    return assess(current, [baseline], settings)
