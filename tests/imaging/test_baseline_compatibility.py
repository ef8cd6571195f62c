"""Baseline and current are compared at the precision that matters physically, and a refusal says by how much.

An API export (geometry through float32) against a file written by hand (float64) was refused:
`circumference_mm differs: baseline 360.02651810139025, current 360.0265197753906` (issue 16, item 5).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from imaging.dimap import BaselineMismatch, check_compatible
from imaging.formats import load_npz, save_npz
from tests.support.synthetic import baseline_and_scatterer


def _as_float32(m):
    """The same measurement as it comes back through a float32 store: every number rounded to 24 bits."""
    f32 = lambda v: float(np.float32(v))  # noqa: E731
    return dataclasses.replace(
        m,
        fs_hz=f32(m.fs_hz), t0_s=f32(m.t0_s), tx_rx_distance_mm=f32(m.tx_rx_distance_mm),
        circumference_mm=f32(m.circumference_mm), rx_angles_deg=m.rx_angles_deg.astype(np.float32).astype(float),
    )


def test_a_float32_round_trip_of_the_same_set_up_is_accepted():
    base, cur = baseline_and_scatterer(200, 90)
    base = dataclasses.replace(base, circumference_mm=360.02651810139025)
    cur = dataclasses.replace(cur, circumference_mm=360.02651810139025)
    exported = _as_float32(cur)
    assert exported.circumference_mm != base.circumference_mm  # 360.0265197753906: the case that was refused
    check_compatible(base, exported)
    check_compatible(_as_float32(base), cur)


def test_files_written_at_two_precisions_analyze_together(tmp_path):
    base, cur = baseline_and_scatterer(200, 90)
    by_hand = load_npz(save_npz(base, tmp_path / "by_hand.npz"))
    exported = load_npz(save_npz(_as_float32(cur), tmp_path / "exported.npz"))
    check_compatible(by_hand, exported)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(circumference_mm=360.0 + 0.35), r"circumference_mm differs by \+0\.350 mm: baseline 360\.000 mm"),
        (dict(tx_rx_distance_mm=400.05), r"tx_rx_distance_mm differs by \+0\.050 mm"),
        (dict(fs_hz=10e6 * (1 + 1e-5)), r"fs_hz differs: baseline 1e\+07 Hz, current 1\.00001e\+07 Hz"),
        (dict(t0_s=0.5e-7), r"t0_s differs by \+0\.5 samples"),
    ],
)
def test_a_real_difference_is_refused_in_physical_units(change, message):
    base, cur = baseline_and_scatterer(200, 90)
    base = dataclasses.replace(base, circumference_mm=360.0, tx_rx_distance_mm=400.0, fs_hz=10e6, t0_s=0.0)
    cur = dataclasses.replace(cur, circumference_mm=360.0, tx_rx_distance_mm=400.0, fs_hz=10e6, t0_s=0.0)
    with pytest.raises(BaselineMismatch, match=message):
        check_compatible(base, dataclasses.replace(cur, **change))


def test_a_moved_receiver_is_named_with_its_distance_on_the_wall():
    base, cur = baseline_and_scatterer(200, 90)
    angles = cur.rx_angles_deg.copy()
    angles[3] += 0.5
    with pytest.raises(BaselineMismatch, match=r"receiver 3 at 67\.500 deg and 68\.000 deg, 0\.\d\d mm apart"):
        check_compatible(base, dataclasses.replace(cur, rx_angles_deg=angles))


def test_angles_either_side_of_zero_are_the_same_receiver():
    base, cur = baseline_and_scatterer(200, 90)
    angles = cur.rx_angles_deg.copy()
    angles[0] = 360.0 - 1e-9
    check_compatible(base, dataclasses.replace(cur, rx_angles_deg=angles))
