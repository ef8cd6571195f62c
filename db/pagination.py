"""Keyset (cursor) pagination over rows in insertion order (id).

A cursor names the last row of a page; the next page starts strictly after it, so rows
inserted meanwhile never shift or repeat pages (unlike OFFSET), and every page is one
index range scan.
"""
from __future__ import annotations

import base64
import binascii
import json
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Generic, TypeVar

from sqlalchemy import Select
from sqlalchemy.orm import InstrumentedAttribute, Session

from db.errors import InvalidCursor

T = TypeVar("T")
MAX_PAGE_SIZE = 1000
_CURSOR_VERSION = 1
# Ids a cursor may name: the signed 64-bit range every backend stores (SQLite's rowid, BIGINT).
_MIN_ID, _MAX_ID = -(2**63), 2**63 - 1
MALFORMED_CURSOR = "malformed cursor: pass back the next_cursor of the previous page unchanged"


@dataclass(frozen=True)
class Page(Generic[T]):
    """One page of rows; ``next_cursor`` is None on the last page."""

    items: list[T]
    next_cursor: str | None


def encode_cursor(at: datetime, row_id: int) -> str:
    payload = json.dumps({"v": _CURSOR_VERSION, "t": at.isoformat(), "id": row_id}, separators=(",", ":"))
    return base64.urlsafe_b64encode(payload.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, int]:
    """(timestamp, id) of a cursor from :func:`encode_cursor`; raises :class:`InvalidCursor`.

    The error says only that the cursor is not one of ours (never a decoder's message), and a
    cursor naming an instant or id no database can compare with is refused here, not by the driver.
    """
    try:
        padded = cursor + "=" * (-len(cursor) % 4)
        payload = json.loads(base64.urlsafe_b64decode(padded.encode("ascii")))
        if payload["v"] != _CURSOR_VERSION:
            raise InvalidCursor("cursor of another version: start from the first page again")
        at = datetime.fromisoformat(payload["t"])
        if at.tzinfo is None or at.utcoffset() is None:
            raise InvalidCursor(MALFORMED_CURSOR)
        at = at.astimezone(UTC)
        row_id = payload["id"]
    except InvalidCursor:
        raise
    except (ValueError, KeyError, TypeError, UnicodeError, binascii.Error, OverflowError, RecursionError):
        raise InvalidCursor(MALFORMED_CURSOR) from None
    if not isinstance(row_id, int) or isinstance(row_id, bool) or not _MIN_ID <= row_id <= _MAX_ID:
        raise InvalidCursor(MALFORMED_CURSOR)
    return at, row_id


def keyset_page(
    session: Session,
    statement: Select[Any],
    *,
    time_column: InstrumentedAttribute[datetime],
    id_column: InstrumentedAttribute[int],
    limit: int,
    cursor: str | None,
    newest_first: bool,
) -> Page[Any]:
    """Run ``statement`` (a select of one entity) one page at a time, in insertion order (``id_column``).

    Not by ``time_column``: a timestamp is what a clock said, and a clock that stepped forward and
    back would put a future-dated row first for as long as the step was (issue 15.1). The cursor
    still carries the row's time (its format is unchanged); only its id places the next page.
    """
    if not 1 <= limit <= MAX_PAGE_SIZE:
        raise ValueError(f"page size must be 1..{MAX_PAGE_SIZE}, got {limit}")
    if cursor is not None:
        _at, row_id = decode_cursor(cursor)
        statement = statement.where(id_column < row_id if newest_first else id_column > row_id)
    statement = statement.order_by(id_column.desc() if newest_first else id_column.asc())
    rows = list(session.scalars(statement.limit(limit + 1)))
    if len(rows) <= limit:
        return Page(items=rows, next_cursor=None)
    items = rows[:limit]
    last = items[-1]
    return Page(items=items, next_cursor=encode_cursor(getattr(last, time_column.key), getattr(last, id_column.key)))
