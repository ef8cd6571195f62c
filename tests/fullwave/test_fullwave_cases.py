"""The project's own case list, the receiver chain applied to it, the cache and the generate command."""
from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fullwave import cache, record
from fullwave.acquisition import acquire_pair, direct_arrival_peak
from fullwave.cases import DECIMATED_FACTOR, own_cases
from fullwave.defects import Mass, Notch
from fullwave.heldout import SPAN_MM, HeldOutError, held_out_cases
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.formats import load_measurement

ROOT = Path(__file__).resolve().parents[2]
DEV_SET_KEYS = {"case", "baseline", "current", "defects", "ends", "transducers", "excitation_hz", "fs_hz",
                "temperature_change_c", "noisy"}
SMALL = SimulationSpec(pipe=PipeModel(length_mm=300.0), rings=RingLayout(tx_axial_mm=50.0, tx_rx_distance_mm=200.0),
                       cell_mm=2.0, n_samples=1500)


def test_case_names_are_unique_and_marked_as_the_projects_own():
    names = [c.name for c in own_cases()]
    assert len(names) == len(set(names)) and all(n.startswith("fw_") for n in names)


def test_every_case_is_a_defect_free_baseline_and_a_current_differing_only_in_defects_and_temperature():
    for case in own_cases():
        assert case.baseline.defects == ()
        assert case.current.with_changes(defects=(), temperature_c=case.baseline.temperature_c) == case.baseline
        entry = case.manifest_entry()
        assert set(entry) >= DEV_SET_KEYS and json.loads(json.dumps(entry)) == entry
        assert len(entry["defects"]) == len(case.defects)
        assert entry["fs_hz"] == 10e6 / case.decimation
        assert case.decimation == 1 or case.noisy  # a decimated record is a noisy one, as in the dev set


def test_the_case_list_covers_what_the_imaging_must_be_judged_on():
    cases = own_cases()
    entries = [c.manifest_entry() for c in cases]
    assert {e["ends"] for e in entries} == {"reflecting", "absorbing"}
    assert {e["transducers"] for e in entries} == {8, 16}
    assert {e["excitation_hz"] for e in entries} == {75e3, 85e3}
    masses = [d for c in cases for d in c.defects if isinstance(d, Mass)]
    assert {m.mass_kg for m in masses} == {10.0, 1.0}  # heavy and light
    assert len({(n.circumferential_mm, n.axial_length_mm, n.depth_mm) for c in cases for n in c.defects
                if isinstance(n, Notch)}) >= 3
    assert any(len(c.defects) == 2 for c in cases)
    changes = {e["temperature_change_c"] for e in entries if e["defects"]}
    assert max(changes) > 0 > min(changes)
    assert any(e["noisy"] for e in entries) and any(e["decimation"] == DECIMATED_FACTOR for e in entries)
    assert sum(1 for e in entries if not e["defects"]) >= 10  # defect-free pairs for false alarms
    assert len({e["tx_axial_mm"] for e in entries}) >= 2  # rings off the pipe's middle too
    in_plane = [e for e in entries if e["model"] == "inplane"]
    assert any(e["tilt_deg"] > 0 for e in in_plane) and any(e["tilt_deg"] == 0 and e["defects"] for e in in_plane)
    assert any(not e["defects"] for e in in_plane)  # mode conversion must not be mistaken for damage either


def test_noisy_pair_has_noise_40_db_below_the_direct_arrival_and_a_10_bit_adc():
    clean = simulate(SMALL)
    baseline, current = acquire_pair(clean, clean, np.random.default_rng(1), noisy=True)
    quiet = slice(0, 100)  # before any wave reaches the Rx ring (200 mm: 64 us)
    noise_rms = float(np.std(baseline.traces[:, quiet]))
    assert noise_rms == pytest.approx(0.01 * direct_arrival_peak(clean), rel=0.05)
    assert not np.array_equal(baseline.traces, current.traces)  # fresh noise per record
    step = np.diff(np.unique(baseline.traces)).min()
    full_scale = 1.2 * np.abs(clean.traces).max()
    assert step == pytest.approx(full_scale / 512, rel=1e-4)
    assert np.unique(baseline.traces).size <= 1024


def test_decimated_pair_keeps_every_tenth_sample_and_a_clean_pair_is_untouched():
    clean = simulate(SMALL)
    same, _ = acquire_pair(clean, clean, np.random.default_rng(0), noisy=False)
    np.testing.assert_array_equal(same.traces, clean.traces)
    decimated, _ = acquire_pair(clean, clean, np.random.default_rng(0), noisy=False, decimation=10)
    assert decimated.fs_hz == 1e6
    np.testing.assert_array_equal(decimated.traces, clean.traces[:, ::10])


def test_simulations_are_cached_by_spec_and_a_damaged_entry_is_recomputed(tmp_path):
    first = cache.cached_simulation(SMALL, tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and files[0].stem == cache.spec_key(SMALL)
    np.testing.assert_array_equal(cache.cached_simulation(SMALL, tmp_path).traces, first.traces)
    assert cache.spec_key(SMALL.with_changes(temperature_c=21.0)) != cache.spec_key(SMALL)
    files[0].write_bytes(b"not a zip file")
    np.testing.assert_array_equal(cache.cached_simulation(SMALL, tmp_path).traces, first.traces)
    assert load_measurement(files[0]).n_samples == SMALL.n_samples


def test_the_code_version_follows_what_the_engine_computes(monkeypatch):
    sh_version, inplane_version = cache.code_version("sh"), cache.code_version("inplane")
    assert sh_version != inplane_version
    original = record.resample

    def rewritten(times_s, samples, fs_hz, n_samples):  # new code, the same arithmetic
        return original(times_s, samples, fs_hz, n_samples)

    monkeypatch.setattr(record, "resample", rewritten)
    cache.code_version.cache_clear()
    assert cache.code_version("sh") == sh_version
    monkeypatch.setattr("fullwave.absorber.THEORETICAL_REFLECTION", 1e-2)  # a weaker absorbing layer
    cache.code_version.cache_clear()
    assert cache.code_version("sh") != sh_version
    cache.code_version.cache_clear()


def test_an_unwritable_cache_is_a_cache_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(cache.CacheError):
        cache.cached_simulation(SMALL, blocker / "cache")


def test_a_held_out_draw_is_reproducible_and_in_neither_set():
    names = [c.name for c in held_out_cases(11, 24)]
    assert names == [c.name for c in held_out_cases(11, 24)]
    assert [c.name for c in held_out_cases(11, 30)][:24] == names  # a longer draw extends a shorter one
    assert len(set(names)) == 24 and all(n.startswith("ho11_") for n in names)
    assert not {c.current for c in held_out_cases(12, 24)} & {c.current for c in held_out_cases(11, 24)}
    assert not {c.current for c in held_out_cases(11, 24)} & {c.current for c in own_cases()}


def test_a_held_out_draw_spans_rings_ends_kinds_and_positions_with_the_records_circumference():
    cases = held_out_cases(3, 60)
    entries = [c.manifest_entry() for c in cases]
    assert all(set(e) >= DEV_SET_KEYS for e in entries)
    assert {(e["transducers"], e["excitation_hz"]) for e in entries} == {(16, 85e3), (8, 75e3)}
    assert {e["ends"] for e in entries} == {"reflecting", "absorbing"} and {e["noisy"] for e in entries} == {True, False}
    defects = [d for c in cases for d in c.defects]
    assert {type(d) for d in defects} == {Notch, Mass} and all(len(c.defects) <= 1 for c in cases)
    assert all(SPAN_MM[0] <= d.axial_mm <= SPAN_MM[1] and 0 <= d.angle_deg < 360 for d in defects)
    free = [e for e in entries if not e["defects"]]
    assert 0 < len(free) < 20 and all(abs(e["temperature_change_c"]) <= 0.7 for e in free)
    assert all(e["temperature_change_c"] == 0.0 for e in entries if e["defects"])
    for case in cases:  # the wave goes round the record's pi x OD, as in the dev set
        assert case.current.pipe.wave_circumference_mm == pytest.approx(np.pi * case.current.pipe.outer_diameter_mm)


@pytest.mark.parametrize("seed, count", [(-1, 3), (1, 0), (1, 501)])
def test_a_held_out_draw_out_of_range_is_refused(seed, count):
    with pytest.raises(HeldOutError):
        held_out_cases(seed, count)


def _run_cli(*args, cache_dir):
    env = {**os.environ, "PIPESENTRY_FULLWAVE_CACHE": str(cache_dir)}
    return subprocess.run([sys.executable, "-m", "fullwave", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=240)


def _documented_line(start: str, option: str = "") -> list[str]:
    """The first command of docs/fullwave.md that starts with ``start`` and uses ``option``, split."""
    for line in (ROOT / "docs" / "fullwave.md").read_text().splitlines():
        if line.startswith(start) and option in line:
            return shlex.split(line)
    raise AssertionError(f"docs/fullwave.md shows no {start} ... {option} command")


def _documented_generate(option: str) -> list[str]:
    """The ``generate`` command of docs/fullwave.md that uses ``option``, as arguments after ``python -m fullwave``."""
    return _documented_line(".venv/bin/python -m fullwave generate", option)[3:]


@pytest.mark.e2e
def test_the_documented_quick_generate_writes_pairs_and_a_manifest_in_the_dev_sets_layout(tmp_path):
    args = _documented_generate("--cell-mm")
    out = tmp_path / "cases"
    args[args.index("--out") + 1] = str(out)
    done = _run_cli(*args, cache_dir=tmp_path / "c")
    assert done.returncode == 0, done.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert [e["case"] for e in manifest["cases"]] == ["fw_m8_absorbing_fa_p06", "fw_m8_absorbing_fa_p06_noisy"]
    for entry in manifest["cases"]:
        assert set(entry) >= DEV_SET_KEYS and entry["defects"] == [] and entry["cell_mm"] == 2.0
        baseline, current = (load_measurement(out / entry[k]) for k in ("baseline", "current"))
        assert baseline.n_rx == current.n_rx == 8 and baseline.temperature_c == 20.0
        assert current.temperature_c == pytest.approx(20.6)
    assert len(list((tmp_path / "c").glob("*.npz"))) == 2  # two simulations serve both cases


@pytest.mark.e2e
def test_the_documented_held_out_generate_writes_a_draw_with_its_truth(tmp_path):
    args = _documented_generate("--held-out")  # its first case only, on a coarse grid
    seed = int(args[args.index("--held-out") + 1])
    args[args.index("--held-out") + 2] = "1"
    out = tmp_path / "held-out"
    args[args.index("--out") + 1] = str(out)
    done = _run_cli(*args, "--cell-mm", "2", cache_dir=tmp_path / "c")
    assert done.returncode == 0, done.stderr
    (entry,) = json.loads((out / "manifest.json").read_text())["cases"]
    (case,) = held_out_cases(seed, 1)
    assert entry["case"] == case.name and entry["defects"] == case.manifest_entry()["defects"] != []
    current = load_measurement(out / entry["current"])
    assert current.circumference_mm == pytest.approx(entry["wave_circumference_mm"], abs=1e-3)
    assert current.n_rx == entry["transducers"]
    bench = _documented_line(".venv/bin/python bench/bench_fullwave.py")  # scored case by case
    bench = [str(out) if a.startswith("../fullwave-heldout") else a for a in bench[1:]]
    scored = subprocess.run([sys.executable, *bench, "--dev", str(out)], cwd=ROOT, capture_output=True, text=True,
                            timeout=240)
    assert scored.returncode == 0, scored.stderr
    assert "### Held-out (held-out, 1 cases)" in scored.stdout and f"| {case.name} | " in scored.stdout


@pytest.mark.e2e
@pytest.mark.parametrize("args", [["generate", "--out", "{tmp}/x", "--cases", "no_such_case"],
                                  ["generate", "--out", "{tmp}/file/x", "--cases", "fw_m8_absorbing_fa_p06"],
                                  ["generate", "--out", "{tmp}/x", "--cell-mm", "0"],
                                  ["list", "--held-out", "-1", "3"]])
def test_generate_refuses_bad_arguments_with_one_line_and_exit_code_2(tmp_path, args):
    (tmp_path / "file").write_text("x")
    done = _run_cli(*[a.format(tmp=tmp_path) for a in args], cache_dir=tmp_path / "c")
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and done.stderr.startswith("error:")
