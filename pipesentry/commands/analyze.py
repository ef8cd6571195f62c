"""`pipesentry analyze`: image a current measurement against a baseline from files."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from pipesentry.errors import fail


def format_summary(result) -> str:
    lines = [f"peak DI {result.peak_di:.6g} ({result.di_map.method}, {result.elapsed_ms:.1f} ms)"]
    for k, d in enumerate(result.defects, 1):
        lines.append(
            f"defect {k}: axial {d.axial_mm:.1f} mm from the Tx ring, angle {d.angle_deg:.1f} deg, DI {d.di:.6g}"
        )
    return "\n".join(lines)


def analyze(
    baseline: Annotated[Path, typer.Option(help="baseline (defect-free) measurement, .npz or .csv")],
    current: Annotated[Path, typer.Option(help="current measurement, .npz or .csv")],
    as_json: Annotated[bool, typer.Option("--json", help="print exactly one JSON object")] = False,
    png: Annotated[Optional[Path], typer.Option(help="write the DI-map heatmap to this PNG file")] = None,
) -> None:
    """Image CURRENT against BASELINE and estimate the defect position."""
    from imaging.analysis import analyze as run_analysis
    from imaging.dimap import BaselineMismatch
    from imaging.formats import load_measurement
    from imaging.measurement import MeasurementError

    try:
        base = load_measurement(baseline)
        cur = load_measurement(current)
        result = run_analysis(base, cur)
    except (MeasurementError, BaselineMismatch) as exc:
        fail(str(exc))
    if png is not None:
        from imaging.heatmap import heatmap_png

        try:
            png.write_bytes(heatmap_png(result.di_map, result.defects))
        except OSError as exc:
            fail(f"cannot write {png}: {exc.strerror or exc}")
    if as_json:
        sys.stdout.write(json.dumps(result.as_json()) + "\n")
    else:
        typer.echo(format_summary(result))
        if png is not None:
            typer.echo(f"heatmap: {png.resolve()}")
