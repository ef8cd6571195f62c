"""Reading and writing measurement files: the .npz interchange format and a CSV form (docs/formats.md)."""
from __future__ import annotations

import csv
import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from imaging.measurement import Measurement, MeasurementError

REQUIRED_KEYS = (
    "traces",
    "fs_hz",
    "t0_s",
    "rx_angles_deg",
    "tx_angles_deg",
    "tx_rx_distance_mm",
    "circumference_mm",
    "velocity_m_s",
    "excitation_hz",
    "cycles",
    "temperature_c",
)
OPTIONAL_KEYS = ("pipe_length_mm", "tx_axial_mm", "wall_mm")
SCALAR_KEYS = tuple(k for k in REQUIRED_KEYS + OPTIONAL_KEYS if k not in ("traces", "rx_angles_deg", "tx_angles_deg"))
CSV_META_KEYS = tuple(k for k in REQUIRED_KEYS + OPTIONAL_KEYS if k not in ("traces", "fs_hz", "t0_s"))
SAMPLING_TOLERANCE = 1e-6  # relative jitter allowed in a CSV time column


class MeasurementFileError(MeasurementError):
    """A measurement file cannot be read: wrong format, missing keys, bad values."""


def _scalar(name: str, value) -> float:
    arr = np.asarray(value)
    if arr.size != 1:
        raise MeasurementFileError(f"{name} must be a scalar, got shape {arr.shape}")
    try:
        return float(arr.reshape(()))
    except (TypeError, ValueError) as exc:
        raise MeasurementFileError(f"{name} is not a number: {value!r}") from exc


def measurement_from_mapping(fields: dict, source: str) -> Measurement:
    """Build a Measurement from format keys (arrays or scalars), with clear errors naming ``source``."""
    missing = [k for k in REQUIRED_KEYS if k not in fields]
    if missing:
        raise MeasurementFileError(f"{source}: missing required key(s): {', '.join(missing)}")
    kwargs: dict[str, Any] = {k: _scalar(k, fields[k]) for k in SCALAR_KEYS if k in fields}
    cycles = kwargs["cycles"]
    if not (math.isfinite(cycles) and cycles == int(cycles)):
        raise MeasurementFileError(f"{source}: cycles must be an integer, got {cycles!r}")
    kwargs["cycles"] = int(cycles)
    try:
        traces = np.asarray(fields["traces"], dtype=np.float32)
        return Measurement(
            traces=traces,
            rx_angles_deg=np.asarray(fields["rx_angles_deg"], dtype=np.float64),
            tx_angles_deg=np.asarray(fields["tx_angles_deg"], dtype=np.float64),
            **kwargs,
        )
    except MeasurementError as exc:
        raise MeasurementFileError(f"{source}: {exc}") from exc
    except (TypeError, ValueError) as exc:
        raise MeasurementFileError(f"{source}: {exc}") from exc


def measurement_fields(m: Measurement) -> dict:
    """The format's keys for a measurement (optional keys only when known)."""
    fields = {
        "traces": m.traces.astype(np.float32),
        "fs_hz": m.fs_hz,
        "t0_s": m.t0_s,
        "rx_angles_deg": m.rx_angles_deg,
        "tx_angles_deg": m.tx_angles_deg,
        "tx_rx_distance_mm": m.tx_rx_distance_mm,
        "circumference_mm": m.circumference_mm,
        "velocity_m_s": m.velocity_m_s,
        "excitation_hz": m.excitation_hz,
        "cycles": m.cycles,
        "temperature_c": m.temperature_c,
    }
    for key in OPTIONAL_KEYS:
        if getattr(m, key) is not None:
            fields[key] = getattr(m, key)
    return fields


def npz_bytes(m: Measurement) -> bytes:
    """The measurement as .npz file contents."""
    buf = io.BytesIO()
    arrays: dict[str, Any] = {k: np.asarray(v) for k, v in measurement_fields(m).items()}
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def save_npz(m: Measurement, path: str | Path) -> Path:
    path = Path(path)
    path.write_bytes(npz_bytes(m))
    return path


def load_npz(path: str | Path) -> Measurement:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            fields = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise MeasurementFileError(f"{path}: no such file") from None
    except ValueError as exc:
        # NumPy falls back to unpickling whatever is not a zip or .npy file, and its refusal then suggests
        # allow_pickle=True: never do that with a file from elsewhere. It is simply not one of ours.
        if "pickle" in str(exc):
            raise MeasurementFileError(
                f"{path}: not a PipeSentry measurement (not a readable .npz file, a zip of NumPy arrays: docs/formats.md)"
            ) from None
        raise MeasurementFileError(f"{path}: not a readable .npz file ({exc})") from exc
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise MeasurementFileError(f"{path}: not a readable .npz file ({exc})") from exc
    return measurement_from_mapping(fields, str(path))


def _parse_meta_value(key: str, text: str):
    text = text.strip()
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = [v for v in text.replace(";", ",").split(",") if v.strip()]
        value = [float(v) for v in value] if len(value) > 1 else (float(value[0]) if value else None)
    if value is None:
        raise MeasurementFileError(f"metadata key {key} has no value")
    return value


def csv_text(m: Measurement) -> str:
    """The CSV form: ``# key: value`` metadata lines, a header, then time_s and one column per receiver."""
    out = io.StringIO()
    for key in CSV_META_KEYS:
        value = getattr(m, key)
        if value is None:
            continue
        if isinstance(value, np.ndarray):
            value = [float(v) for v in value]
        elif isinstance(value, float) and math.isnan(value):
            value = "NaN"
        out.write(f"# {key}: {json.dumps(value) if not isinstance(value, str) else value}\n")
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["time_s"] + [f"rx{i}" for i in range(m.n_rx)])
    t = m.t0_s + np.arange(m.n_samples) / m.fs_hz
    for k in range(m.n_samples):
        writer.writerow([repr(float(t[k]))] + [repr(float(v)) for v in m.traces[:, k]])
    return out.getvalue()


def load_csv(path: str | Path) -> Measurement:
    """Read the CSV form; metadata from ``# key: value`` lines and/or a side-car ``<name>.json``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise MeasurementFileError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MeasurementFileError(f"{path}: cannot read ({exc})") from exc
    meta: dict = {}
    sidecar = path.with_suffix(".json")
    if sidecar.exists():
        try:
            meta.update(json.loads(sidecar.read_text()))
        except (OSError, json.JSONDecodeError) as exc:
            raise MeasurementFileError(f"{sidecar}: bad side-car JSON ({exc})") from exc
    rows = []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, sep, value = stripped.lstrip("#").partition(":")
            if sep and key.strip():
                meta[key.strip()] = _parse_meta_value(key.strip(), value)
            continue
        rows.append(stripped)
    if len(rows) < 3:
        raise MeasurementFileError(f"{path}: needs a header row and at least two samples")
    try:
        table = np.array([[float(v) for v in r.split(",")] for r in rows[1:]], dtype=np.float64)
    except ValueError as exc:
        raise MeasurementFileError(f"{path}: non-numeric sample ({exc})") from exc
    if table.ndim != 2 or table.shape[1] < 2:
        raise MeasurementFileError(f"{path}: rows have different numbers of columns or no receiver column")
    header = [h.strip() for h in rows[0].split(",")]
    if len(header) != table.shape[1]:
        raise MeasurementFileError(f"{path}: header has {len(header)} columns, data has {table.shape[1]}")
    t = table[:, 0]
    dt = np.diff(t)
    if not np.all(np.isfinite(t)) or np.any(dt <= 0):
        raise MeasurementFileError(f"{path}: the time column must increase strictly")
    step = float(np.mean(dt))
    if np.max(np.abs(dt - step)) > SAMPLING_TOLERANCE * step + 1e-15:
        raise MeasurementFileError(f"{path}: the time column is not uniformly sampled")
    fields = dict(meta)
    fields["traces"] = table[:, 1:].T
    fields["fs_hz"] = 1.0 / step
    fields["t0_s"] = float(t[0])
    fields.setdefault("temperature_c", math.nan)
    return measurement_from_mapping(fields, str(path))


def load_measurement(path: str | Path) -> Measurement:
    """Load a .npz or .csv measurement file, raising MeasurementFileError with a clear message."""
    suffix = Path(path).suffix.lower()
    if suffix == ".npz":
        return load_npz(path)
    if suffix == ".csv":
        return load_csv(path)
    raise MeasurementFileError(f"{path}: unknown file type {suffix!r} (expected .npz or .csv)")
