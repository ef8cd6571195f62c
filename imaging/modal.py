"""Remove the low circumferential orders of a residual across the receiver ring (modal clutter filter).

A guided mode travels along the pipe with a fixed pattern round it: order n arrives at every
receiver of the Rx ring at the same instant, weighted cos(n theta) or sin(n theta). Residual
arrivals of that kind are not T(0,1) scattered by a point between the rings (whose arrival
time changes from receiver to receiver): the axisymmetric L(0,1), L(0,2) and T(0,1) arrivals
left by an imperfect temperature compensation, ring leakage, and what a defect converts into
the low flexural orders F(1,m), F(2,m), all of which the T(0,1) path model would place near
the Tx ring or at the wrong distance. At every time sample this module fits the orders
0..n_max across the healthy receivers (least squares) and subtracts them.

The cost: 2 n_max + 1 of the ring's N degrees of freedom per sample, taken from the defect's
echo as well (most from a defect near the Tx ring, whose echo arrives almost together at all
receivers). ``default_modal_orders`` keeps that to at most a fifth of the ring (MAX_SHARE):
n_max = 1 for 16 receivers, 0 (the axisymmetric part only) for 8, none below 5. See docs/imaging.md.
"""
from __future__ import annotations

import numpy as np

from imaging.health import receiver_rows


class ModalError(ValueError):
    """Bad arguments to the modal filter."""


MAX_SHARE = 0.2  # of the ring's degrees of freedom the filter may take


def default_modal_orders(n_rx: int) -> int | None:
    """The largest n_max with 2 n_max + 1 <= MAX_SHARE n_rx (16 -> 1, 8 -> 0), None below 5 receivers."""
    budget = int(MAX_SHARE * n_rx + 1e-9)
    if budget < 1:
        return None
    return (budget - 1) // 2


def order_basis(rx_angles_deg: np.ndarray, max_order: int) -> np.ndarray:
    """[n_rx, 2 max_order + 1]: 1, cos(n theta), sin(n theta) for n = 1..max_order."""
    theta = np.radians(np.asarray(rx_angles_deg, dtype=np.float64))
    cols = [np.ones_like(theta)]
    for n in range(1, max_order + 1):
        cols += [np.cos(n * theta), np.sin(n * theta)]
    return np.stack(cols, axis=1)


def remove_low_orders(residual: np.ndarray, rx_angles_deg: np.ndarray, max_order: int,
                      rx_mask: np.ndarray | None = None) -> np.ndarray:
    """``residual`` [n_rx, n_samples] with circumferential orders 0..max_order removed on the healthy rows.

    Rows outside ``rx_mask`` are returned unchanged (they are not imaged). With fewer healthy
    receivers than 2 max_order + 2 nothing is removed (the fit would swallow everything).
    """
    residual = np.asarray(residual, dtype=np.float64)
    if residual.ndim != 2:
        raise ModalError("residual must be [n_rx, n_samples]")
    if max_order < 0:
        raise ModalError(f"max_order must be >= 0, got {max_order}")
    mask = receiver_rows(residual.shape[0], rx_mask)
    basis = order_basis(rx_angles_deg, max_order)[mask]
    if basis.shape[0] < basis.shape[1] + 1:
        return residual.copy()
    # Projection onto the orders' span via an orthonormal basis of the healthy rows.
    q, _ = np.linalg.qr(basis)
    out = residual.copy()
    rows = residual[mask]
    out[mask] = rows - q @ (q.T @ rows)
    return out


def axisymmetric_fraction(residual: np.ndarray, rx_mask: np.ndarray | None = None) -> float:
    """The share of ``residual``'s energy [n_rx, n_samples] common to the healthy receivers (order 0:
    the same arrival at every receiver at the same instant); 0 for an empty residual.

    What changes the pipe or the ring as a whole (its ends, what lies beyond the rings, the ring's
    gain, another pipe's reference) is axisymmetric; a point defect between the rings scatters a
    field whose arrival changes from receiver to receiver. Measured on the full-wave dev and own sets
    (2026-12-03, bench/bench_reference_check.py): every strong defect 0.05-0.47 (most on 8-rings, whose
    few receivers keep more of any field in their mean); a baseline of the same pipe with other ends
    0.80-1.00."""
    residual = np.asarray(residual, dtype=np.float64)
    mask = receiver_rows(residual.shape[0], rx_mask)
    rows = residual[mask]
    energy = float(np.sum(rows * rows))
    if rows.shape[0] == 0 or not energy > 0:
        return 0.0
    common = rows.mean(axis=0)
    return rows.shape[0] * float(np.sum(common * common)) / energy
