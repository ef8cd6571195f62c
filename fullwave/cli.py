"""``python -m fullwave generate --out DIR``: the project's own full-wave cases as files.

Writes ``<case>_baseline.npz`` / ``<case>_current.npz`` and a ``manifest.json`` in the dev set's
layout (so one scorer reads both), simulating what the cache (fullwave/cache.py) lacks.
``--held-out SEED COUNT`` writes a seeded random draw of cases in neither set instead
(fullwave/heldout.py). ``list`` prints the case names. Exit codes: 0 done, 2 bad arguments or an unwritable directory
(one line on stderr).
"""
from __future__ import annotations

import argparse
import fnmatch
import json
import sys
import time
from pathlib import Path
from typing import TextIO

from fullwave.cache import CacheError, case_pair, code_version
from fullwave.cases import CASE_CELL_MM, Case, own_cases
from fullwave.heldout import HeldOutError, held_out_cases
from fullwave.record import SimulationError
from imaging.formats import npz_bytes

DESCRIPTION = "PipeSentry full-wave cases: 2-D FDTD of the unrolled pipe wall (fullwave/, docs/fullwave.md)"


class UsageError(ValueError):
    """Arguments that select nothing or point nowhere."""


def select(cases: list[Case], patterns: list[str] | None) -> list[Case]:
    """Cases whose name matches any of the shell-style ``patterns`` (all when none are given)."""
    if not patterns:
        return cases
    chosen = [c for c in cases if any(fnmatch.fnmatchcase(c.name, p) for p in patterns)]
    if not chosen:
        raise UsageError(f"no case matches {' '.join(patterns)} (see: python -m fullwave list)")
    return chosen


def generate(out_dir: Path, cases: list[Case], cache_dir: Path | None, log: TextIO | None = sys.stderr) -> dict:
    """Write every case's pair and the manifest into ``out_dir``; returns the manifest. One progress
    line per case goes to ``log`` (None: quiet)."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CacheError(f"cannot create {out_dir}: {exc.strerror or exc}") from exc
    entries = []
    for k, case in enumerate(cases, 1):
        started = time.perf_counter()
        baseline, current = case_pair(case, cache_dir)
        entry = case.manifest_entry()
        try:
            (out_dir / entry["baseline"]).write_bytes(npz_bytes(baseline))
            (out_dir / entry["current"]).write_bytes(npz_bytes(current))
        except OSError as exc:
            raise CacheError(f"cannot write into {out_dir}: {exc.strerror or exc}") from exc
        entries.append(entry)
        if log is not None:
            print(f"[{k}/{len(cases)}] {case.name} {time.perf_counter() - started:.1f} s", file=log, flush=True)
    versions = ", ".join(f"{model} {code_version(model)}" for model in sorted({c.current.model for c in cases}))
    manifest = {"description": f"{DESCRIPTION}; engine {versions}", "cases": entries}
    try:
        (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    except OSError as exc:
        raise CacheError(f"cannot write {out_dir / 'manifest.json'}: {exc.strerror or exc}") from exc
    return manifest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fullwave", description=DESCRIPTION)
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="write the cases' .npz pairs and manifest.json into --out")
    gen.add_argument("--out", required=True, type=Path, help="output directory (created if missing)")
    gen.add_argument("--cases", nargs="+", metavar="PATTERN", help="only cases matching these shell patterns")
    gen.add_argument("--cell-mm", type=float, default=None,
                     help=f"grid cell instead of the cases' {CASE_CELL_MM} mm (e.g. 2 for a quick, coarse look)")
    gen.add_argument("--cache", type=Path, default=None,
                     help="simulation cache (default: $PIPESENTRY_FULLWAVE_CACHE or out/fullwave-cache)")
    lister = sub.add_parser("list", help="print the case names")
    lister.add_argument("--cases", nargs="+", metavar="PATTERN")
    for command in (gen, lister):
        command.add_argument("--held-out", nargs=2, type=int, metavar=("SEED", "COUNT"), default=None,
                             help="a seeded random draw of COUNT cases in neither set instead of the own cases")
    args = parser.parse_args(argv)
    try:
        cases = select(own_cases() if args.held_out is None else held_out_cases(*args.held_out), args.cases)
        if args.command == "list":
            print("\n".join(c.name for c in cases))
            return 0
        if args.cell_mm is not None:
            if not 0.1 <= args.cell_mm <= 5.0:
                raise UsageError(f"--cell-mm must be 0.1..5 mm, got {args.cell_mm}")
            cases = [c.with_cell(args.cell_mm) for c in cases]
        generate(args.out, cases, args.cache)
    except (UsageError, HeldOutError, CacheError, SimulationError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


__all__ = ["generate", "main", "select"]
