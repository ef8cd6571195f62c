"""A sparse Tx ring's incident wave fitted to a defect-free record: the wrap length and the pipe ends.

``imaging.arrivals.end_reflection_coefficients`` reads them off the matched envelope at the
end echoes' arrival time, relative to the direct arrival. That holds for an axisymmetric
incident wave. A sparse ring (imaging/paths.py ``sparse_ring``) also launches order N, which
near its cut-off travels at a fraction of c: on the paper's pipe its direct arrival reaches the
Rx ring with the end echoes (measured on the full-wave dev set's 8-ring records: free ends read
0.30, absorbing ones 0.71). Here the record is fitted instead: on every receiver the direct
wave, the near-end echo and the far-end echo, each the sum of every Tx element image's
cylindrical wave (the map's own incident model), with one complex amplitude per route shared
by the receivers; a coefficient is the ratio of an echo's amplitude to the direct wave's.

The same fit measures the wrap length. Order N's cut-off N c / C sits just below the burst's
band, so its slow, dispersive arrival depends steeply on the circumference C the wave travels:
a node reports pi x OD, the wave travels the mid-wall pi (OD - wall), 3.5 % less on the paper's
pipe, which moves the 8-ring's cut-off from 69.6 to 72.1 kHz. Without a wall thickness
(``wall_mm``), ``fit_sparse_ring`` takes the C in [0.85, 1.0] x the record's circumference whose
model explains most of the record (grid of 0.5 % steps, then a parabola through the best three),
if it stands out: it must leave at most DECISIVE (0.7) of the scan's median unexplained, else the
record's circumference is kept. Measured (2026-12-03): the SH full-wave records' minimum sits
at the true wrap with 0.48-0.64 of the median (dev 360 mm, own 347.4); the own in-plane model's
8-ring record (tilted patches: S0 and mode conversion too) has a flat, many-minima curve (best
0.76 of the median, at 0.905 x 360 mm, the true 0.965 not even a local minimum): kept at 360.

``RingFit.plane_unexplained`` is the same fit with an axisymmetric plane wave from the ring:
imaging/multipath.py ``path_model_for`` models the ring element by element only where the
element model explains the baseline clearly better (``ELEMENTS_EVIDENCE``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from imaging.echofit import burst_pair
from imaging.measurement import Measurement
from imaging.paths import PathFamily, PathModel, incident_terms
from imaging.timing import MM_PER_M


def _route_waves(m: Measurement, model: PathModel, family: PathFamily) -> np.ndarray:
    """[2, n_rx, n]: the route's incident wave at each receiver (burst and quadrature twin), cut to the record."""
    shapes = np.stack(burst_pair(m.fs_hz, m.excitation_hz, m.cycles))
    size = shapes.shape[1]
    n = m.n_samples
    rx_arc = np.asarray(m.rx_angles_deg, dtype=np.float64) * (model.circumference_mm / 360.0)
    out = np.zeros((2, m.n_rx, n + 2 * size))
    c_mm_s = m.velocity_m_s * MM_PER_M
    for length, weight in incident_terms(model, np.full(m.n_rx, m.tx_rx_distance_mm), rx_arc, family):
        k = np.floor((length / c_mm_s - m.t0_s) * m.fs_hz + 0.5).astype(np.int64)
        for r in np.flatnonzero((k < n) & (k + size > 0) & (weight > 0)):
            out[:, r, size + k[r]:size + k[r] + size] += weight[r] * shapes
    return out[:, :, size:size + n]


class RingFit(NamedTuple):
    """What ``fit_sparse_ring`` measured: the wrap length (mm), the ends' coefficients, and the share of the
    record's energy the fitted incident model leaves unexplained."""

    circumference_mm: float
    near: float
    far: float
    unexplained: float
    plane_unexplained: float = math.nan  # the same fit with an axisymmetric plane wave from the ring


WRAP_SCAN = np.linspace(0.85, 1.0, 31)  # fractions of the record's circumference tried as the wrap length
DECISIVE = 0.7  # ... and the best must leave at most this fraction of the scan's median unexplained


def _fit(m: Measurement, model: PathModel, near_end_mm: float | None, far_end_mm: float | None) -> RingFit:
    d = m.tx_rx_distance_mm
    direct = PathFamily("direct", 0.0, 1.0, d, 1.0)
    if near_end_mm is None or far_end_mm is None:  # ends unknown: the direct wave alone
        near_end_mm, far_end_mm = -m.n_samples / m.fs_hz * m.velocity_m_s * MM_PER_M, m.n_samples / m.fs_hz * m.velocity_m_s * MM_PER_M
    near = PathFamily("near", -2.0 * near_end_mm, 1.0, d, 1.0)
    far = PathFamily("far", 2.0 * far_end_mm, -1.0, d, 1.0)
    burst_mm = m.cycles / m.excitation_hz * m.velocity_m_s * MM_PER_M
    near_path, far_path = d - 2.0 * near_end_mm, 2.0 * far_end_mm - d
    together = abs(near_path - far_path) < burst_mm
    routes = [_route_waves(m, model, direct)]
    echoes = ([_route_waves(m, model, near) + _route_waves(m, model, far)] if together
              else [_route_waves(m, model, near), _route_waves(m, model, far)])
    present = [bool(np.any(e)) for e in echoes]
    routes += [e for e, p in zip(echoes, present, strict=True) if p]
    design = np.stack([shape.ravel() for wave in routes for shape in wave], axis=1)  # [n_rx n, 2 routes]
    record = np.asarray(m.traces, dtype=np.float64).ravel()
    coef, *_ = np.linalg.lstsq(design, record, rcond=None)
    left = record - design @ coef
    unexplained = float(left @ left) / max(float(record @ record), 1e-300)
    amplitude = np.hypot(coef[0::2], coef[1::2])
    if amplitude[0] <= 0:
        return RingFit(model.circumference_mm, 1.0, 1.0, unexplained)
    ratios = iter(amplitude[1:] / amplitude[0])
    raw = [float(next(ratios)) if p else None for p in present]
    if together:  # one column holds both echoes, each of weight 1: its amplitude is each end's
        value = 1.0 if raw[0] is None else min(raw[0], 1.0)
        return RingFit(model.circumference_mm, value, value, unexplained)
    near_value, far_value = (1.0 if r is None else min(r, 1.0) for r in raw)
    return RingFit(model.circumference_mm, near_value, far_value, unexplained)


def _with_wrap(model: PathModel, m: Measurement, circumference_mm: float) -> PathModel:
    arcs = tuple(float(a) * circumference_mm / 360.0 for a in m.tx_angles_deg)
    return dataclasses.replace(model, circumference_mm=circumference_mm, tx_arcs_mm=arcs)


def fit_sparse_ring(m: Measurement, model: PathModel, near_end_mm: float | None, far_end_mm: float | None, *,
                    fit_wrap: bool) -> RingFit:
    """The wrap length (``fit_wrap``; else ``model``'s) and (near, far) coefficients in [0, 1] of a defect-free
    record ``m`` of a ring imaged with ``model`` (its Tx elements), remembered with the record.

    ``near_end_mm`` <= 0 and ``far_end_mm`` >= the Rx ring: the ends' positions from the Tx ring (None:
    unknown; the direct wave alone is fitted, and the coefficients read 1.0).
    When the two echoes reach the Rx ring within a burst of each other (the paper's pipe: both
    after 1000 mm) they are one column, the two echoes' sum, and share one coefficient. An echo
    wholly outside the record reads 1.0 (unknown: keep its paths).
    """
    key = (*m.traces_digest(), model, near_end_mm, far_end_mm, fit_wrap, m.fs_hz, m.t0_s, m.velocity_m_s,
           m.excitation_hz, m.cycles)

    def compute() -> RingFit:
        plane = _fit(m, dataclasses.replace(model, tx_arcs_mm=()), near_end_mm, far_end_mm).unexplained
        return _elements()._replace(plane_unexplained=plane)

    def _elements() -> RingFit:
        if not fit_wrap:
            return _fit(m, model, near_end_mm, far_end_mm)
        scan = [_fit(m, _with_wrap(model, m, f * m.circumference_mm), near_end_mm, far_end_mm) for f in WRAP_SCAN]
        left = np.array([f.unexplained for f in scan])
        best = int(np.argmin(left))
        if left[best] > DECISIVE * float(np.median(left)):  # no wrap length stands out: keep the record's
            return _fit(m, model, near_end_mm, far_end_mm)
        if 0 < best < len(scan) - 1:  # a parabola through the best three
            y0, y1, y2 = (scan[best + k].unexplained for k in (-1, 0, 1))
            curvature = y0 - 2.0 * y1 + y2
            if curvature > 0:
                step = float(WRAP_SCAN[1] - WRAP_SCAN[0])
                fraction = float(WRAP_SCAN[best]) + 0.5 * step * (y0 - y2) / curvature
                refined = _fit(m, _with_wrap(model, m, fraction * m.circumference_mm), near_end_mm, far_end_mm)
                if refined.unexplained <= scan[best].unexplained:
                    return refined
        return scan[best]

    return m.derived("sparse_ring_fit", key, compute)
