"""Command-line start-up: how long ``pipesentry --help`` (and a subcommand's) takes, against a bare Python.

Run: ``.venv/bin/python bench/bench_cli.py [-n 15]``. Each command runs as its own process;
the figures are medians of wall and CPU (user + system) time. CPU time is what the command
costs; wall time also holds whatever else the machine is doing. Target (issue 14): ``--help``
under 0.3 s (it was ~1 s when the mock node's physics was imported to build the command line).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
COMMANDS = {
    "python -c pass": [sys.executable, "-c", "pass"],
    "pipesentry --help": [str(BIN / "pipesentry"), "--help"],
    "pipesentry analyze --help": [str(BIN / "pipesentry"), "analyze", "--help"],
    "pipesentry mock-node --help": [str(BIN / "pipesentry"), "mock-node", "--help"],
}
TARGET_S = 0.3


def measure(command: list[str], n: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``n`` runs of ``command``."""
    walls, cpus = [], []
    for _ in range(n):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.perf_counter()
        subprocess.run(command, capture_output=True, check=True, timeout=60)
        walls.append(time.perf_counter() - started)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=15, help="runs per command")
    args = parser.parse_args()
    print(f"command-line start-up, median of {args.n} runs (wall / CPU):")
    results = {name: measure(command, args.n) for name, command in COMMANDS.items()}
    for name, (wall, cpu) in results.items():
        print(f"  {name:28s} {wall * 1e3:6.0f} ms / {cpu * 1e3:5.0f} ms")
    wall, cpu = results["pipesentry --help"]
    verdict = "met" if cpu < TARGET_S else "MISSED"
    print(f"pipesentry --help: {cpu * 1e3:.0f} ms CPU, {wall * 1e3:.0f} ms wall (target < {TARGET_S * 1e3:.0f} ms: "
          f"{verdict} on CPU)")


if __name__ == "__main__":
    main()
