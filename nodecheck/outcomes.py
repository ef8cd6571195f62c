"""What one requirement came to, and the line the checker prints for it (pure)."""
from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from nodecheck.requirements import Requirement


class Status(StrEnum):
    PASSED = "passed"
    FAILED = "FAILED"
    NOT_APPLICABLE = "n/a"


@dataclass(frozen=True)
class Outcome:
    requirement: Requirement
    status: Status
    note: str = ""  # why it failed, or what was not applicable
    evidence: str = ""  # the bytes that failed, hex

    def line(self) -> str:
        """One line: id, status, the requirement, and what failed with its bytes (or why n/a)."""
        text = f"{self.requirement.id:<10} {self.status.value:<6} {self.requirement.text}"
        if self.note:
            text += f": {self.note}" if self.status == Status.FAILED else f" ({self.note})"
        if self.evidence:
            text += f" [bytes: {self.evidence}]"
        return text


class Failure(Exception):
    """Raised by a check: the requirement is not met; ``evidence`` is the offending bytes in hex."""

    def __init__(self, detail: str, evidence: str = "") -> None:
        super().__init__(detail)
        self.detail = detail
        self.evidence = evidence


@dataclass(frozen=True)
class NotApplicable:
    """Returned by a check whose requirement does not apply to this node (a capability, a version)."""

    reason: str


def expect(condition: object, detail: str, evidence: str = "") -> None:
    if not condition:
        raise Failure(detail, evidence)


def all_passed(outcomes: list[Outcome]) -> bool:
    return all(o.status != Status.FAILED for o in outcomes)
