"""The default method on independent full-wave physics: the dev set and the project's own cases.

Scores what ``pipesentry analyze`` runs (``imaging.analysis.analyze`` with the file's wall
thickness) on every case of the full-wave development set (``../shared/fullwave-dev``, truth in
its manifest.json) and of PipeSentry's own full-wave cases (``fullwave.cases.own_cases()``, read
from ``../fullwave-own`` as ``python -m fullwave generate`` writes it; with ``--own-cache DIR``
simulated through that cache instead). Prints per class (transducers x end condition x defect
kind; noisy / decimated / temperature variants; two defects; defect-free) the worst and median
localization error, detections, false alarms, the margin ratio (weakest detected defect's DI /
largest defect-free peak of the same ring and ends), and how often the truth lies inside the
reported 90 % region, with the region's median size.

Error: surface distance (wrap-aware, on the record's circumference) from each true defect to the
nearest reported defect; a defect with no reported defect within MATCH_MM is "missed" (its error
is then to the map's peak, shown in brackets). A reported defect farther than MATCH_MM from
every true one is a false alarm.

    .venv/bin/python bench/bench_fullwave.py [--dev DIR] [--own DIR | --own-cache DIR] [--cases PATTERN ...] [--no-thermometer]
                                             [--own-16-wall-mm MM] [--threshold DI] [--held-out DIR ...]

``--held-out DIR ...`` also scores each set in the dev set's layout that neither holds, as ``python -m
fullwave generate --held-out SEED COUNT --out DIR`` draws it (fullwave/heldout.py), in a table of
its own, case by case (not in the dev + own totals; several sets also together).

The own 16-transducer records (whose files, like a node's, carry no wall thickness) are imaged as a
node configured with the wall they were simulated with (``--own-16-wall-mm``, default 4 mm), as
docs/gateway.md asks for a 16-ring node: its wrap cannot be fitted (its baseline is a plane wave),
and without it the wrap is pi x OD, 3.5 % longer than the own wave's, which moves defects on records
without end echoes by 20-50 mm. ``--own-16-wall-mm 0`` images them as the files are (the default
until 2026-12-06). The 8-transducer records keep their files' missing wall: their wrap is fitted.

The dev set is not in the repository: without it the benchmark says so and exits 0, except
under CI=true (exit 1). Own cases missing from --own are listed as missing, not scored.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import fnmatch  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

from fullwave.record import PipeModel  # noqa: E402
from imaging.analysis import analyze  # noqa: E402
from imaging.detection import default_threshold  # noqa: E402
from imaging.formats import load_measurement  # noqa: E402
from imaging.measurement import Measurement  # noqa: E402
from imaging.pipeline import Assessment  # noqa: E402
from imaging.timing import surface_distance_mm  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DEV = REPO.parent / "shared" / "fullwave-dev"
DEFAULT_OWN = REPO.parent / "fullwave-own"
MATCH_MM = 50.0  # a reported defect this close to a true one is that defect's detection
OWN_WALL_MM = PipeModel().wall_mm  # the wall the own cases are simulated with: their wave wraps at pi (OD - wall)


@dataclass
class Scored:
    """One case's outcome."""

    source: str
    name: str
    klass: str
    ring: str  # transducers, ends and model: the defect-free peak a detection is compared with
    errors: list[float]  # per true defect: to its detection, or to the peak when missed
    detected: list[bool]
    detected_di: list[float]
    in_region: list[bool]  # per detected true defect
    region_mm: list[float]  # per detected true defect: axial + circumferential half-widths (mean)
    unlocalized: list[bool]  # per detected true defect: the output says it cannot be localized
    false_alarms: int
    peak_di: float
    elapsed_ms: float
    abstained: bool = False
    notes: list[str] = field(default_factory=list)


def class_of(entry: dict) -> tuple[str, str]:
    """(class label, ring label) of a manifest entry."""
    ring = f"{'ip ' if entry.get('model') == 'inplane' else ''}n{entry['transducers']} {entry['ends']}"
    defects = entry["defects"]
    if not defects:
        kind = "defect-free"
    elif len(defects) > 1:
        kind = "two defects"
    else:
        d = defects[0]
        kind = d["kind"]
        if d["kind"] == "mass" and "1 kg" in d.get("size", ""):
            kind = "light mass"
    variant = []
    if entry.get("decimation", 1) > 1 or entry.get("fs_hz", 10e6) < 5e6:
        variant.append("decim")
    elif entry.get("noisy"):
        variant.append("noisy")
    if defects and entry.get("temperature_change_c", 0.0):
        variant.append("dT")
    if entry.get("tilt_deg"):
        variant.append("tilt")
    return f"{ring} {kind}{' ' + '+'.join(variant) if variant else ''}", ring


def score(source: str, entry: dict, baseline: Measurement, current: Measurement, thermometer: bool = True,
          wall_mm: float | None = None, threshold: float | None = None) -> Scored:
    """``wall_mm``: the configured wall for a file that carries none; ``threshold`` None: the default."""
    started = time.perf_counter()
    wall = current.wall_mm if current.wall_mm is not None else wall_mm
    result: Assessment = analyze(baseline, current, wall_mm=wall, thermometer=thermometer, threshold=threshold)
    elapsed = (time.perf_counter() - started) * 1e3
    klass, ring = class_of(entry)
    circ = current.circumference_mm
    truth = [(float(d["axial_mm"]), float(d["angle_deg"])) for d in entry["defects"]]
    reported = result.defects
    errors, detected, detected_di, in_region, region_mm, unlocalized = [], [], [], [], [], []
    used: set[int] = set()
    for z, a in truth:
        dist = [surface_distance_mm(d.axial_mm, d.angle_deg, z, a, circ) for d in reported]
        k = min(range(len(dist)), key=dist.__getitem__) if dist else None
        if k is not None and dist[k] <= MATCH_MM:
            d = reported[k]
            used.add(k)
            errors.append(dist[k])
            detected.append(True)
            detected_di.append(d.di)
            region = getattr(d, "region", None)
            if region is not None:
                in_region.append(region.contains(d.axial_mm, d.angle_deg, z, a, circ))
                region_mm.append(0.5 * (region.axial_half_mm + region.circumferential_half_mm))
                unlocalized.append(not region.localized)
        else:
            peak = result.peak
            errors.append(surface_distance_mm(peak.axial_mm, peak.angle_deg, z, a, circ) if peak else float("nan"))
            detected.append(False)
    false_alarms = sum(1 for k in range(len(reported)) if k not in used)
    return Scored(source, entry["case"], klass, ring, errors, detected, detected_di, in_region, region_mm,
                  unlocalized, false_alarms, float(result.peak_di or 0.0), elapsed,
                  abstained=not result.valid_baseline)


def dev_cases(root: Path) -> Iterator[tuple[dict, Measurement, Measurement]]:
    manifest = json.loads((root / "manifest.json").read_text())
    for entry in manifest["cases"]:
        yield entry, load_measurement(root / entry["baseline"]), load_measurement(root / entry["current"])


def own_entries() -> list[tuple[dict, object]]:
    from fullwave.cases import own_cases

    return [(case.manifest_entry(), case) for case in own_cases()]


def own_from_files(root: Path, missing: list[str]) -> Iterator[tuple[dict, Measurement, Measurement]]:
    for entry, _case in own_entries():
        b, c = root / entry["baseline"], root / entry["current"]
        if not (b.is_file() and c.is_file()):
            missing.append(entry["case"])
            continue
        yield entry, load_measurement(b), load_measurement(c)


def own_from_cache(cache: Path) -> Iterator[tuple[dict, Measurement, Measurement]]:
    from fullwave.cache import case_pair

    for entry, case in own_entries():
        baseline, current = case_pair(case, cache)  # type: ignore[arg-type]
        yield entry, baseline, current


def _fmt(values: list[float]) -> str:
    return f"{statistics.median(values):.1f} / {max(values):.1f}" if values else "-"


def table(rows: list[Scored], title: str) -> list[str]:
    """Markdown lines: one row per class, then the totals."""
    free_peak: dict[str, float] = {}
    for r in rows:
        if not r.errors and not r.abstained:
            free_peak[r.ring] = max(free_peak.get(r.ring, 0.0), r.peak_di)
    overall_free = max(free_peak.values(), default=0.0)
    out = [f"### {title}", "",
           "| class | cases | detected | error median / worst (mm) | missed: error to peak (mm) | false alarms | "
           "margin (weakest DI / largest free peak) | 90 % region: hit / median half-width (mm) | flagged |",
           "|---|---|---|---|---|---|---|---|---|"]
    classes: dict[str, list[Scored]] = {}
    for r in rows:
        classes.setdefault(r.klass, []).append(r)
    for klass in sorted(classes):
        group = classes[klass]
        n_true = sum(len(r.errors) for r in group)
        hits = [e for r in group for e, d in zip(r.errors, r.detected, strict=True) if d]
        misses = [e for r in group for e, d in zip(r.errors, r.detected, strict=True) if not d]
        fa = sum(r.false_alarms for r in group)
        weakest = min((di for r in group for di in r.detected_di), default=None)
        ring_free = free_peak.get(group[0].ring, overall_free) or overall_free
        if n_true == 0:
            margin = f"peak {max(r.peak_di for r in group):.4f}"
        elif weakest is None or ring_free <= 0:
            margin = "-"
        else:
            margin = f"{weakest / ring_free:.1f}x"
        inside = [x for r in group for x in r.in_region]
        sizes = [x for r in group for x in r.region_mm]
        region = f"{sum(inside)}/{len(inside)} / {statistics.median(sizes):.1f}" if inside else "-"
        flagged = sum(x for r in group for x in r.unlocalized)
        abstain = sum(r.abstained for r in group)
        out.append(f"| {klass}{f' ({abstain} abstained)' if abstain else ''} | {len(group)} | {len(hits)}/{n_true} | "
                   f"{_fmt(hits)} | {', '.join(f'{e:.0f}' for e in misses) or '-'} | {fa} | {margin} | {region} | "
                   f"{flagged} |")
    hits = [e for r in rows for e, d in zip(r.errors, r.detected, strict=True) if d]
    single = [e for r in rows if len(r.errors) == 1 for e, d in zip(r.errors, r.detected, strict=True) if d]
    two = [e for r in rows if len(r.errors) > 1 for e, d in zip(r.errors, r.detected, strict=True) if d]
    n_true = sum(len(r.errors) for r in rows)
    inside = [x for r in rows for x in r.in_region]
    sizes = [x for r in rows for x in r.region_mm]
    detected_di = [di for r in rows for di in r.detected_di]
    out += ["",
            f"- detected {len(hits)}/{n_true} defects; single-defect error median / worst {_fmt(single)} mm; "
            f"two-defect cases {_fmt(two)} mm",
            f"- false alarms: {sum(r.false_alarms for r in rows if not r.errors)} in "
            f"{sum(1 for r in rows if not r.errors)} defect-free records, "
            f"{sum(r.false_alarms for r in rows if r.errors)} spurious beside true defects; largest defect-free peak "
            f"{overall_free:.4f}; weakest detected DI {min(detected_di, default=float('nan')):.4f}",
            f"- 90 % regions: truth inside {sum(inside)}/{len(inside)} "
            f"({100 * sum(inside) / len(inside) if inside else float('nan'):.0f} %), median half-width "
            f"{statistics.median(sizes) if sizes else float('nan'):.1f} mm",
            f"- analyze() median {statistics.median(r.elapsed_ms for r in rows):.0f} ms per case", ""]
    return out


def case_lines(rows: list[Scored]) -> list[str]:
    """Markdown lines: one row per case (for a set nobody has looked at yet)."""
    out = ["| case | error per true defect (mm) | reported beside them | flagged | peak DI |", "|---|---|---|---|---|"]
    for r in rows:
        errors = ", ".join(f"{e:.1f}" if d else f"missed ({e:.0f})" for e, d in zip(r.errors, r.detected, strict=True))
        out.append(f"| {r.name} | {errors or '-'} | {r.false_alarms} | {sum(r.unlocalized)} | {r.peak_di:.4f} |")
    return out + [""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dev", type=Path, default=DEFAULT_DEV, help=f"dev set (default {DEFAULT_DEV})")
    parser.add_argument("--own", type=Path, default=DEFAULT_OWN, help=f"own cases' files (default {DEFAULT_OWN})")
    parser.add_argument("--own-cache", type=Path, default=None,
                        help="simulate the own cases through this full-wave cache instead of reading --own")
    parser.add_argument("--cases", nargs="+", metavar="PATTERN", help="only cases matching these shell patterns")
    parser.add_argument("--skip-own", action="store_true", help="the dev set only")
    parser.add_argument("--no-thermometer", action="store_true",
                        help="leave the stretch to the search even on strong changes (AssessSettings.thermometer)")
    parser.add_argument("--own-16-wall-mm", type=float, default=OWN_WALL_MM, metavar="MM",
                        help=f"image the own 16-transducer records as a node configured with this wall thickness "
                             f"(default {OWN_WALL_MM:g}, the simulated wall; 0: as the files are, without)")
    parser.add_argument("--threshold", type=float, default=None, metavar="DI",
                        help="detection threshold instead of the method's default (imaging/detection.py)")
    parser.add_argument("--held-out", type=Path, nargs="+", default=[], metavar="DIR",
                        help="also score these sets (dev layout, e.g. python -m fullwave generate --held-out ...)")
    args = parser.parse_args(argv)
    for held_out_dir in args.held_out:
        if not (held_out_dir / "manifest.json").is_file():
            print(f"bench_fullwave: no manifest.json in {held_out_dir}", file=sys.stderr)
            return 2
    if not (args.dev / "manifest.json").is_file():
        print(f"bench_fullwave: the full-wave dev set is absent ({args.dev}/manifest.json): nothing scored",
              file=sys.stderr)
        return 1 if os.environ.get("CI", "").lower() == "true" else 0

    def wanted(entry: dict) -> bool:
        return not args.cases or any(fnmatch.fnmatchcase(entry["case"], p) for p in args.cases)

    started = time.perf_counter()
    load = os.getloadavg()[0]
    thermometer = not args.no_thermometer
    threshold = args.threshold
    dev = [score("dev", e, b, c, thermometer, threshold=threshold) for e, b, c in dev_cases(args.dev) if wanted(e)]
    own: list[Scored] = []
    missing: list[str] = []
    if not args.skip_own:
        source = own_from_cache(args.own_cache) if args.own_cache else own_from_files(args.own, missing)
        wall = args.own_16_wall_mm or None
        own = [score("own", e, b, c, thermometer, wall if e["transducers"] == 16 else None, threshold)
               for e, b, c in source if wanted(e)]
    lines = table(dev, f"Dev set ({args.dev.name}, {len(dev)} cases)") if dev else []
    if own:
        lines += table(own, f"Own full-wave cases ({len(own)} cases)")
    if dev and own:
        lines += table(dev + own, f"Dev + own ({len(dev) + len(own)} cases)")
    held_out: list[Scored] = []
    for held_out_dir in args.held_out:
        rows = [score("held-out", e, b, c, thermometer, threshold=threshold) for e, b, c in dev_cases(held_out_dir) if wanted(e)]
        if rows:
            lines += table(rows, f"Held-out ({held_out_dir.name}, {len(rows)} cases)") + case_lines(rows)
        held_out += rows
    if len(args.held_out) > 1 and held_out:
        lines += table(held_out, f"Held-out, all ({len(held_out)} cases)")
    if not (dev or own or held_out):
        lines.append(f"bench_fullwave: no case matches {' '.join(args.cases or [])}")
    print("\n".join(lines))
    if missing:
        print(f"own cases not found in {args.own} (not scored): {len(missing)}: {', '.join(missing)}")
    used = f"{threshold:g}" if threshold is not None else f"{default_threshold('multipath', 'analytic'):g} (the default)"
    print(f"threshold {used}; run time {time.perf_counter() - started:.0f} s, load average at start {load:.1f} "
          f"({os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
