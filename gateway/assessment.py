"""The gateway's imaging of one monitor measurement: the node's baseline library, the settings, the verdict.

Pure apart from reading baseline traces through the database session it is given.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from db.measurement_build import NodeGeometryView, measurement_from_codes
from db.measurements import get_measurement, load_traces
from db.models import MapSource, NodeState
from db.records import DetectionInput, DiMapInput, MapGrid
from gateway.config import NodeSettings
from gateway.record_settings import RecordSettings
from imaging.compensation import NoValidBaseline
from imaging.measurement import Measurement
from imaging.pipeline import Assessment, AssessSettings


class BaselineLibrary:
    """A node's defect-free references for optimal baseline selection, decoded (``db.baselines.
    library_baseline_ids`` names them: the active one first). Decoded traces are cached by id."""

    def __init__(self) -> None:
        self._cache: dict[int, Measurement] = {}
        self._settings: dict[int, RecordSettings] = {}

    def settings(self, ids: list[int]) -> list[RecordSettings]:
        """The settings each loaded baseline was taken with, in the order of ``ids``."""
        return [self._settings[i] for i in ids]

    def load(self, session: Session, ids: list[int], view: NodeGeometryView) -> list[Measurement]:
        for stale in set(self._cache) - set(ids):
            del self._cache[stale]
            self._settings.pop(stale, None)
        out = []
        for measurement_id in ids:
            if measurement_id not in self._cache:
                row = get_measurement(session, measurement_id)
                self._settings[measurement_id] = RecordSettings(
                    row.excitation_hz, row.cycles, row.averaging, row.n_channels, row.n_samples, row.fs_hz, row.t0_s)
                self._cache[measurement_id] = measurement_from_codes(
                    load_traces(row),
                    row.volts_per_code,
                    fs_hz=row.fs_hz,
                    t0_s=row.t0_s,
                    view=view,
                    channels=None,
                    excitation_hz=row.excitation_hz,
                    cycles=row.cycles,
                    temperature_c=row.temperature_c,
                )
            out.append(self._cache[measurement_id])
        return out


LIBRARY_MARGIN = 0.5  # a measurement joins the library only if its peak DI is below half the threshold


def joins_library(
    node: NodeSettings,
    *,
    state: NodeState,
    peak_di: float | None,
    threshold: float | None,
    temperature_c: float | None,
    library: list[Measurement],
    baseline_age_days: float,
) -> bool:
    """Whether a monitor measurement becomes another baseline of the node's OBS library.

    Only a clearly healthy reading (state ok, peak DI below half the threshold), at a
    temperature at least ``library_temperature_step_c`` from every baseline in the library,
    while the library has room and the active baseline is younger than
    ``library_growth_days``: the library learns the seasons without learning a growing defect.
    """
    im = node.imaging
    if im.library_temperature_step_c <= 0 or len(library) >= im.library_size:
        return False
    if baseline_age_days > im.library_growth_days or state != NodeState.OK:
        return False
    if peak_di is None or threshold is None or not peak_di < LIBRARY_MARGIN * threshold:
        return False
    if temperature_c is None or not math.isfinite(temperature_c):
        return False
    known = [b.temperature_c for b in library if math.isfinite(b.temperature_c)]
    return all(abs(temperature_c - t) >= im.library_temperature_step_c for t in known)


def assess_settings(node: NodeSettings, threshold: float | None, wall_mm: float | None) -> AssessSettings:
    """The node's imaging settings; the gateway's damage threshold is also the detection threshold."""
    im = node.imaging
    extra: dict[str, Any] = {} if im.max_residual is None else {"max_residual": im.max_residual}
    return AssessSettings(
        method=im.method,
        feature=im.feature,
        compensate=im.compensate,
        threshold=threshold,
        max_defects=im.max_defects,
        modal_orders=im.modal_orders,
        thermometer=im.thermometer,
        max_compensated_stretch=im.max_compensated_stretch,
        wall_mm=wall_mm,
        **extra,
    )


def abstained(settings: AssessSettings, reason: str) -> Assessment:
    """An assessment that made no map, for ``reason`` (the record is comparable with no baseline):
    stored and decided on like any imaging that abstains."""
    return Assessment(settings.method, settings.feature, settings.effective_threshold, None, None, [], None,
                      NoValidBaseline(None, math.nan, math.nan, reason), [], 0.0)


def gateway_map(result: Assessment, library_ids: list[int]) -> DiMapInput | None:
    """The gateway's own DI map of the assessment, as stored (None when the imaging abstained)."""
    if result.di_map is None or result.baseline is None:
        return None
    return DiMapInput(
        source=MapSource.GATEWAY,
        method=result.method,
        grid=MapGrid(**result.di_map.grid.spec()),
        pixels=result.di_map.pixels.astype(np.float32),
        baseline_measurement_id=library_ids[result.baseline.index],
    )


def detection_input(
    result: Assessment, state: NodeState, threshold: float | None, library_ids: list[int]
) -> DetectionInput:
    """What is stored as the verdict on the measurement."""
    peak = result.peak
    baseline_id = stretch = None
    if result.baseline is not None:
        baseline_id = library_ids[result.baseline.index]
        stretch = result.baseline.stretch
    confidence = None
    if result.defects:
        confidence = _finite(result.defects[0].confidence.as_dict().get("score"))
    return DetectionInput(
        peak_di=_finite(result.peak_di),
        threshold=threshold,
        state=state,
        axial_mm=None if peak is None else peak.axial_mm,
        angle_deg=None if peak is None else peak.angle_deg,
        confidence=confidence,
        method=result.method,
        defects=[_json_safe(d.as_dict()) for d in result.defects],
        sensor_faults=[_json_safe(f.as_dict()) for f in result.sensor_faults],
        baseline_measurement_id=baseline_id,
        stretch=stretch,
        abstain_reason=None if result.no_valid_baseline is None else result.no_valid_baseline.reason,
    )


def _finite(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _json_safe(value):
    """Plain JSON types: NaN/inf become None (JSON has no such numbers)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if hasattr(value, "item"):
        return _json_safe(value.item())
    return value
