"""What every chaos case shares: reduced or full size, and the counts it prints.

The normal suite runs each case reduced but real; ``make chaos`` (PIPESENTRY_CHAOS_FULL=1) runs
the full loops. Each case prints one line: faults injected, records checked, lost, duplicated,
corrupted; lost, duplicated and corrupted must be 0.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

FULL = os.environ.get("PIPESENTRY_CHAOS_FULL") == "1"


def size(reduced: int, full: int) -> int:
    """How many of something a case does: ``full`` under ``make chaos``, else ``reduced``."""
    return full if FULL else reduced


@dataclass
class Counts:
    case: str
    faults: int = 0
    checked: int = 0
    lost: int = 0
    duplicated: int = 0
    corrupted: int = 0

    def report(self, **extra: object) -> str:
        more = "".join(f", {k} {v}" for k, v in extra.items())
        line = (f"chaos {self.case}: faults injected {self.faults}, records checked {self.checked}, lost {self.lost}, "
                f"duplicated {self.duplicated}, corrupted {self.corrupted}{more}")
        print(line)
        return line

    def assert_nothing_lost(self) -> None:
        assert (self.lost, self.duplicated, self.corrupted) == (0, 0, 0), self.report()
        assert self.checked > 0, f"{self.case}: nothing was checked"
