"""Measurement files: the .npz interchange format and the CSV form, with clear errors for bad files."""
import json
import math

import numpy as np
import pytest

from imaging.formats import MeasurementFileError, csv_text, load_measurement, save_npz
from tests.support.synthetic import baseline_and_scatterer


@pytest.fixture
def meas():
    return baseline_and_scatterer(200, 90, n_rx=4, n_samples=300)[1]



def test_npz_round_trip_keeps_every_field(tmp_path, meas):
    back = load_measurement(save_npz(meas, tmp_path / "m.npz"))
    np.testing.assert_array_equal(back.traces, meas.traces)
    for key in ("fs_hz", "t0_s", "tx_rx_distance_mm", "circumference_mm", "velocity_m_s", "excitation_hz", "cycles"):
        assert getattr(back, key) == getattr(meas, key)
    np.testing.assert_array_equal(back.rx_angles_deg, meas.rx_angles_deg)
    assert back.pipe_length_mm is None and back.tx_axial_mm is None


def test_npz_keeps_optional_pipe_fields_and_ignores_extra_keys(tmp_path, meas):
    data = dict(np.load(save_npz(meas, tmp_path / "m.npz")))
    data.update(pipe_length_mm=1000.0, tx_axial_mm=300.0, operator_note=np.array("hello"))
    np.savez(tmp_path / "x.npz", **data)
    back = load_measurement(tmp_path / "x.npz")
    assert back.pipe_length_mm == 1000.0 and back.tx_axial_mm == 300.0


def test_the_wall_thickness_travels_with_the_record_in_npz_and_csv(tmp_path, meas):
    from dataclasses import replace

    walled = replace(meas, wall_mm=6.02)
    assert load_measurement(save_npz(walled, tmp_path / "m.npz")).wall_mm == 6.02
    (tmp_path / "m.csv").write_text(csv_text(walled))
    assert load_measurement(tmp_path / "m.csv").wall_mm == 6.02
    assert load_measurement(save_npz(meas, tmp_path / "none.npz")).wall_mm is None


def test_nan_temperature_means_unknown(tmp_path, meas):
    data = dict(np.load(save_npz(meas, tmp_path / "m.npz")))
    data["temperature_c"] = np.nan
    np.savez(tmp_path / "x.npz", **data)
    assert math.isnan(load_measurement(tmp_path / "x.npz").temperature_c)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("fs_hz"), "missing required key.*fs_hz"),
        (lambda d: d.__setitem__("traces", np.full((4, 300), np.nan, np.float32)), "NaN/inf"),
        (lambda d: d.__setitem__("rx_angles_deg", np.zeros(3)), "rx_angles_deg has 3 entries"),
        (lambda d: d.__setitem__("traces", np.zeros(300, np.float32)), "2-D"),
        (lambda d: d.__setitem__("fs_hz", np.array(-1.0)), "fs_hz must be a positive"),
        (lambda d: d.__setitem__("cycles", np.array(2.5)), "cycles must be an integer"),
        (lambda d: d.__setitem__("wall_mm", np.array(-4.0)), "wall_mm must be a positive"),
        (lambda d: d.update(pipe_length_mm=500.0, tx_axial_mm=300.0), "beyond pipe_length_mm"),
    ],
)
def test_bad_npz_gives_a_clear_error(tmp_path, meas, mutate, message):
    data = dict(np.load(save_npz(meas, tmp_path / "m.npz")))
    mutate(data)
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(MeasurementFileError, match=message):
        load_measurement(tmp_path / "bad.npz")


def test_garbage_file_is_not_a_readable_npz(tmp_path):
    (tmp_path / "g.npz").write_bytes(b"\x00garbage" * 10)
    with pytest.raises(MeasurementFileError, match=r"not a readable \.npz"):
        load_measurement(tmp_path / "g.npz")


def test_csv_round_trip_with_header_metadata(tmp_path, meas):
    (tmp_path / "m.csv").write_text(csv_text(meas))
    back = load_measurement(tmp_path / "m.csv")
    np.testing.assert_allclose(back.traces, meas.traces, rtol=1e-7)
    assert back.fs_hz == pytest.approx(meas.fs_hz, rel=1e-9)
    assert back.t0_s == pytest.approx(meas.t0_s, abs=1e-15)
    np.testing.assert_allclose(back.rx_angles_deg, meas.rx_angles_deg)


def test_csv_with_side_car_metadata_as_exported_from_a_scope(tmp_path, meas):
    t = 5e-6 + np.arange(meas.n_samples) / meas.fs_hz
    lines = ["time_s,ch1,ch2,ch3,ch4"] + [
        ",".join([f"{t[k]:.10e}"] + [f"{v:.7g}" for v in meas.traces[:, k]]) for k in range(meas.n_samples)
    ]
    (tmp_path / "scope.csv").write_text("\n".join(lines))
    side = {
        "rx_angles_deg": [0, 90, 180, 270],
        "tx_angles_deg": [0, 90, 180, 270],
        "tx_rx_distance_mm": 400,
        "circumference_mm": 360.03,
        "velocity_m_s": 3130,
        "excitation_hz": 75000,
        "cycles": 5,
    }
    (tmp_path / "scope.json").write_text(json.dumps(side))
    back = load_measurement(tmp_path / "scope.csv")
    assert back.t0_s == pytest.approx(5e-6)
    assert back.excitation_hz == 75000 and math.isnan(back.temperature_c)


@pytest.mark.parametrize(
    "body, message",
    [
        ("time_s,rx0\n0,1\n1e-7,oops\n2e-7,3\n", "non-numeric"),
        ("time_s,rx0\n0,1\n2e-7,2\n1e-7,3\n", "increase strictly"),
        ("time_s,rx0\n0,1\n1e-7,2\n3e-7,3\n", "not uniformly sampled"),
        ("time_s,rx0\n0,1\n", "at least two samples"),
    ],
)
def test_bad_csv_gives_a_clear_error(tmp_path, body, message):
    (tmp_path / "b.csv").write_text(body)
    with pytest.raises(MeasurementFileError, match=message):
        load_measurement(tmp_path / "b.csv")


def test_csv_without_metadata_names_the_missing_keys(tmp_path):
    (tmp_path / "b.csv").write_text("time_s,rx0\n0,1\n1e-7,2\n2e-7,3\n")
    with pytest.raises(MeasurementFileError, match=r"missing required key.*rx_angles_deg"):
        load_measurement(tmp_path / "b.csv")


def test_unknown_extension_and_missing_file(tmp_path):
    with pytest.raises(MeasurementFileError, match="unknown file type"):
        load_measurement(tmp_path / "m.mat")
    with pytest.raises(MeasurementFileError, match="no such file"):
        load_measurement(tmp_path / "absent.npz")
