"""`pipesentry analyze`: image a current measurement against a baseline from files."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Annotated

import typer

from pipesentry.errors import fail


def format_summary(result) -> str:
    from imaging.compensation import DEFAULT_MAX_COMPENSATED_STRETCH

    lines = [
        f"peak DI {result.peak_di:.6g} ({result.method}, threshold {result.threshold:.4g}, {result.elapsed_ms:.1f} ms)"
    ]
    if result.baseline is not None and result.baseline.stretch:
        lines.append(f"baseline stretched by {result.baseline.stretch * 100:+.4f} % (temperature compensation)")
        if abs(result.baseline.stretch) > DEFAULT_MAX_COMPENSATED_STRETCH:
            lines.append(f"caution: beyond the {DEFAULT_MAX_COMPENSATED_STRETCH:.2%} the gateway compensates reliably "
                         "(it would abstain): weak peaks may be temperature, not the pipe")
    for fault in result.sensor_faults:
        lines.append(f"sensor fault: receiver {fault.rx_index} at {fault.rx_angle_deg:.1f} deg ({fault.kind}), left out")
    if not result.defects:
        p = result.peak
        lines.append(f"no defect detected (strongest point: axial {p.axial_mm:.1f} mm, angle {p.angle_deg:.1f} deg)")
    for k, d in enumerate(result.defects, 1):
        lines.append(
            f"defect {k}: axial {d.axial_mm:.1f} mm from the Tx ring, angle {d.angle_deg:.1f} deg, DI {d.di:.6g}, "
            f"severity {d.severity:.3g}, confidence {d.confidence.score:.2f}"
        )
        region = d.region
        lines.append(f"  {region.coverage:.0%} region: +-{region.axial_half_mm:.0f} mm axial, "
                     f"+-{region.circumferential_half_mm:.0f} mm round the pipe"
                     + ("" if region.localized else f"; position not resolved: {region.reason}"))
    return "\n".join(lines)


def _prepare_output(png: Path) -> None:
    """Create the PNG's directory (``out/`` on a fresh clone) and refuse a path that cannot be written."""
    try:
        png.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(f"cannot write {png}: {exc.strerror or exc} ({png.parent})")
    if png.is_dir():
        fail(f"cannot write {png}: it is a directory")
    if not os.access(png.parent, os.W_OK | os.X_OK):
        fail(f"cannot write {png}: no permission to write in {png.parent}")


def analyze(
    baseline: Annotated[Path, typer.Option(help="baseline (defect-free) measurement, .npz or .csv")],
    current: Annotated[Path, typer.Option(help="current measurement, .npz or .csv")],
    as_json: Annotated[bool, typer.Option("--json", help="print exactly one JSON object")] = False,
    png: Annotated[
        Path | None, typer.Option(help="write the DI-map heatmap to this PNG file (its directory is created)")
    ] = None,
    method: Annotated[str, typer.Option(help="multipath (all paths, default) or paper (Algorithm 1)")] = "multipath",
    feature: Annotated[str, typer.Option(help="multipath feature: analytic (default), envelope or squared")] = "analytic",
    threshold: Annotated[float | None, typer.Option(help="detection threshold (default: documented per method)")] = None,
    max_defects: Annotated[int, typer.Option(help="report at most this many defects")] = 3,
    wall_mm: Annotated[
        float | None, typer.Option(help="pipe wall thickness, for the mid-wall wrap length (default: the file's wall_mm)")
    ] = None,
    compensate: Annotated[bool, typer.Option(help="stretch the baseline to the current temperature")] = True,
) -> None:
    """Image CURRENT against BASELINE and estimate the defect positions."""
    from imaging.analysis import analyze as run_analysis
    from imaging.dimap import BaselineMismatch
    from imaging.formats import load_measurement
    from imaging.measurement import MeasurementError
    from imaging.multipath import MultipathError
    from imaging.pipeline import SettingsError

    if png is not None:
        _prepare_output(png)  # before the work: a path that cannot be written fails now, not after the map
    try:
        base = load_measurement(baseline)
        cur = load_measurement(current)
        result = run_analysis(
            base, cur, method=method, feature=feature, threshold=threshold, max_defects=max_defects,
            compensate=compensate, wall_mm=cur.wall_mm if wall_mm is None else wall_mm,
        )
    except (MeasurementError, BaselineMismatch, SettingsError, MultipathError) as exc:
        fail(str(exc))
    if png is not None:
        from imaging.heatmap import MapMark, heatmap_png

        if result.di_map is None or result.peak is None:
            fail(f"no map to draw: {result.no_valid_baseline.reason if result.no_valid_baseline else 'no map'}")
        try:
            marks: list[MapMark] = [*result.defects] or [result.peak]
            # Below the threshold the cross is the map's strongest point, not a defect's estimate.
            label = "estimate" if result.defects else "map peak (below threshold)"
            png.write_bytes(heatmap_png(result.di_map, marks, label=label, threshold=result.threshold))
        except OSError as exc:
            fail(f"cannot write {png}: {exc.strerror or exc}")
    if as_json:
        sys.stdout.write(json.dumps(result.as_json()) + "\n")
    else:
        typer.echo(format_summary(result))
        if png is not None:
            typer.echo(f"heatmap: {png.resolve()}")
