"""DI maps of a measurement: the grid and pixels as JSON, and a PNG heatmap with the estimate marked."""
from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from db.errors import NotFound
from db.measurements import get_measurement, load_pixels
from db.models import DiMapRow, MapSource
from db.queries import detection_for
from imaging.detection import DEFAULT_THRESHOLDS
from imaging.dimap import DIMap
from imaging.grid import Grid
from imaging.heatmap import heatmap_png
from imaging.localize import Estimate, locate_peak
from service import schemas

# The feature is not stored with a map; while a node calibrates, its colours use the default of the
# gateway's default feature (analytic), an approximation that lasts only until the threshold exists.
DEFAULT_FEATURE = "analytic"
PNG_CACHE_ENTRIES = 64  # a stored map never changes, so its PNG can be kept (~60 kB each)


def map_row(session: Session, measurement_id: int, source: MapSource) -> DiMapRow:
    get_measurement(session, measurement_id)
    row = session.scalars(
        select(DiMapRow)
        .where(DiMapRow.measurement_id == measurement_id, DiMapRow.source == source)
        .order_by(DiMapRow.id.desc())
        .limit(1)
    ).first()
    if row is None:
        raise NotFound(f"measurement {measurement_id} has no DI map from the {source.value}")
    return row


def _di_map(row: DiMapRow) -> DIMap:
    # window_samples is not stored with a map; 0 marks it unknown (it is not needed to draw).
    return DIMap(pixels=load_pixels(row), grid=Grid.from_spec(row.grid), method=row.method, window_samples=0)


def _estimate(session: Session, row: DiMapRow, di_map: DIMap) -> Estimate | None:
    """The gateway's map: the defect estimate stored with the verdict; the node's map: its peak."""
    if row.source == MapSource.GATEWAY:
        detection = detection_for(session, row.measurement_id)
        if detection is None or detection.axial_mm is None or detection.angle_deg is None or detection.peak_di is None:
            return None
        return Estimate(detection.axial_mm, detection.angle_deg, detection.peak_di)
    pixels = di_map.pixels
    finite = np.isfinite(pixels)
    if not finite.any():
        return None
    filled = np.where(finite, pixels, np.nanmin(np.where(finite, pixels, np.nan)))
    return locate_peak(DIMap(filled, di_map.grid, di_map.method, di_map.window_samples))


def _marker_label(session: Session, row: DiMapRow) -> str:
    """What the cross on a map means: a defect estimate only when the verdict found one."""
    if row.source != MapSource.GATEWAY:
        return "node's peak"
    detection = detection_for(session, row.measurement_id)
    return "estimate" if detection is not None and detection.defects else "map peak (below threshold)"


def _colour_scale(session: Session, row: DiMapRow) -> tuple[float | None, str]:
    """The threshold the map's colours are scaled to, and what to call it on the colour bar.

    The gateway's map: the verdict's threshold (the node's), or while calibrating the method's
    documented default. The node's own map is in other units (the on-board paper DI): its own range."""
    if row.source != MapSource.GATEWAY:
        return None, ""
    detection = detection_for(session, row.measurement_id)
    if detection is not None and detection.threshold is not None:
        return detection.threshold, "threshold"
    default = DEFAULT_THRESHOLDS.get((row.method, DEFAULT_FEATURE))
    return default, "default threshold (calibrating)"


def map_json(session: Session, measurement_id: int, source: MapSource) -> schemas.DiMap:
    row = map_row(session, measurement_id, source)
    di_map = _di_map(row)
    estimate = _estimate(session, row, di_map)
    pixels = [[v if math.isfinite(v) else None for v in line] for line in di_map.pixels.astype(float).tolist()]
    return schemas.DiMap(
        **schemas.DiMapSummary.model_validate(row).model_dump(),
        measurement_id=row.measurement_id,
        grid=schemas.Grid(**di_map.grid.spec()),
        pixels=pixels,
        estimate=None if estimate is None else schemas.Estimate(
            axial_mm=estimate.axial_mm, angle_deg=estimate.angle_deg, di=estimate.di
        ),
    )


class HeatmapRenderer:
    """Draws map PNGs one at a time (pyplot is not thread-safe) and keeps the recent ones."""

    def __init__(self, entries: int = PNG_CACHE_ENTRIES) -> None:
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple, bytes] = OrderedDict()
        self._entries = entries

    def png(self, session: Session, measurement_id: int, source: MapSource) -> bytes:
        row = map_row(session, measurement_id, source)
        di_map = _di_map(row)
        estimate = _estimate(session, row, di_map)
        label = _marker_label(session, row)
        threshold, threshold_label = _colour_scale(session, row)
        key = (row.id, row.pixels_sha256, label, threshold,
               None if estimate is None else (estimate.axial_mm, estimate.angle_deg))
        with self._lock:
            cached = self._cache.get(key)
            if cached is not None:
                self._cache.move_to_end(key)
                return cached
            title = f"{row.measurement.node_id} measurement {measurement_id}: {source.value} DI map ({row.method})"
            png = heatmap_png(di_map, [] if estimate is None else [estimate], title=title, label=label,
                              threshold=threshold, threshold_label=threshold_label)
            self._cache[key] = png
            while len(self._cache) > self._entries:
                self._cache.popitem(last=False)
            return png
