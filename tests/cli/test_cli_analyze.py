"""`pipesentry analyze`: the human summary, exactly one JSON object, the heatmap, and exit 2 on bad input."""
import json
import subprocess
import sys

import pytest

from imaging.formats import save_npz
from imaging.timing import surface_distance_mm
from tests.support.synthetic import CIRCUMFERENCE_MM, baseline_and_scatterer

pytestmark = pytest.mark.e2e  # runs the system's real processes


def run_cli(*args, timeout_s=60):
    return subprocess.run(
        [sys.executable, "-m", "pipesentry", *map(str, args)], capture_output=True, text=True, timeout=timeout_s
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("analyze")
    base, cur = baseline_and_scatterer(230.0, 200.0)
    return save_npz(base, d / "baseline.npz"), save_npz(cur, d / "current.npz"), d


def test_json_output_is_one_object_with_the_defect_first(files):
    base, cur, _ = files
    proc = run_cli("analyze", "--baseline", base, "--current", cur, "--json")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)  # exactly one JSON document: json.loads rejects trailing data
    assert set(result) >= {"peak_di", "defects", "grid", "elapsed_ms", "method"}
    d = result["defects"][0]
    assert surface_distance_mm(d["axial_mm"], d["angle_deg"], 230.0, 200.0, CIRCUMFERENCE_MM) < 5.0
    assert result["grid"]["axial_count"] == 401 and result["grid"]["angle_count"] == 360
    assert result["peak_di"] == pytest.approx(max(x["di"] for x in result["defects"]))


def test_human_summary_and_png_heatmap(files):
    base, cur, d = files
    png = d / "map.png"
    proc = run_cli("analyze", "--baseline", base, "--current", cur, "--png", png)
    assert proc.returncode == 0, proc.stderr
    assert "defect 1: axial" in proc.stdout and str(png) in proc.stdout
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_missing_file_exits_2_with_one_line(files):
    _, cur, d = files
    proc = run_cli("analyze", "--baseline", d / "absent.npz", "--current", cur)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "no such file" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_mismatched_baseline_exits_2(files):
    base, _, d = files
    _, short_cur = baseline_and_scatterer(200.0, 90.0, n_samples=4000)
    other = save_npz(short_cur, d / "short.npz")
    proc = run_cli("analyze", "--baseline", base, "--current", other, "--json")
    assert proc.returncode == 2 and proc.stdout == ""
    assert "differ in shape" in proc.stderr and "Traceback" not in proc.stderr


def test_corrupt_file_exits_2(files):
    base, _, d = files
    bad = d / "corrupt.npz"
    bad.write_bytes(base.read_bytes()[:500])
    proc = run_cli("analyze", "--baseline", base, "--current", bad)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: ")


def test_the_png_directory_is_created_like_out_on_a_fresh_clone(files):
    base, cur, d = files
    png = d / "out" / "sub" / "example.png"
    proc = run_cli("analyze", "--baseline", base, "--current", cur, "--png", png)
    assert proc.returncode == 0, proc.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_unwritable_png_path_exits_2_before_the_map_is_computed(files):
    base, cur, _ = files
    proc = run_cli("analyze", "--baseline", base, "--current", cur, "--png", base / "x.png")  # under a file
    assert proc.returncode == 2 and "cannot write" in proc.stderr and "Traceback" not in proc.stderr
    assert proc.stdout == ""  # refused before the work: no summary was printed


def test_a_file_that_is_not_a_measurement_never_suggests_unpickling_it(files):
    _, cur, d = files
    text = d / "notes.npz"
    text.write_text("baseline taken on Monday\n")
    proc = run_cli("analyze", "--baseline", text, "--current", cur)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "not a PipeSentry measurement" in proc.stderr
    assert "pickle" not in proc.stderr.lower()


def test_a_pair_far_apart_in_temperature_is_imaged_with_a_caution():
    from imaging.pipeline import AssessSettings, assess
    from pipesentry.commands.analyze import format_summary
    from tests.support.synthetic import mock_pipe_record as record

    text = format_summary(assess(record(45.0, 2), [record(20.0, 1)], AssessSettings(wall_mm=4.0)))
    assert "baseline stretched by +0.2" in text and "caution: beyond the 0.15%" in text
    near = format_summary(assess(record(22.0, 2), [record(20.0, 1)], AssessSettings(wall_mm=4.0)))
    assert "caution" not in near


@pytest.mark.parametrize("method", ["paper", "multipath"])
def test_a_png_without_a_defect_calls_its_cross_the_map_peak_not_an_estimate(files, tmp_path, monkeypatch, method):
    """A sub-threshold noise peak was labelled "estimate 1" on the paper-method PNG (issue 16, item 9)."""
    from typer.testing import CliRunner

    import imaging.heatmap
    from pipesentry.cli import app

    base, _, _ = files
    drawn: list[dict] = []
    real = imaging.heatmap.heatmap_png
    monkeypatch.setattr(imaging.heatmap, "heatmap_png", lambda m, marks, **kw: drawn.append(kw) or real(m, marks, **kw))
    png = tmp_path / "same.png"
    result = CliRunner().invoke(app, ["analyze", "--baseline", str(base), "--current", str(base), "--method", method,
                                      "--png", str(png)])
    assert result.exit_code == 0, result.output
    assert "no defect detected" in result.output
    assert drawn[0]["label"] == "map peak (below threshold)" and drawn[0]["threshold"] > 0
