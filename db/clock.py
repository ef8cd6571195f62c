"""The one place storage reads the wall clock (tests pass explicit times instead)."""
from __future__ import annotations

from datetime import UTC, datetime


def utc_now() -> datetime:
    """Now, as a timezone-aware UTC datetime."""
    return datetime.now(UTC)
