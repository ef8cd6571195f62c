"""Path and query parameters shared by the routes: paging, time ranges, ids.

Every parameter is range-checked here, at the edge: a value that passes reaches the database
as something it can store and compare (an instant in UTC within Python's datetime range, an
id within the 53 bits every JSON client can represent), so valid-looking input such as
``9999-12-31T23:59:59-14:00`` is a 422 problem, never a 500.
"""
from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import Path, Query
from pydantic import AfterValidator, AwareDatetime

from db.pagination import MAX_PAGE_SIZE
from service.schemas import MAX_ID

DEFAULT_LIMIT = 50


def in_utc(value: datetime) -> datetime:
    """The instant in UTC; ValueError (422) when it lies outside the years 1..9999 there."""
    try:
        return value.astimezone(UTC)
    except OverflowError:
        raise ValueError("the instant is outside the years 1 to 9999 in UTC") from None


Instant = Annotated[AwareDatetime, AfterValidator(in_utc)]
Limit = Annotated[int, Query(ge=1, le=MAX_PAGE_SIZE, description="page size")]
Cursor = Annotated[str | None, Query(max_length=512, description="next_cursor of the previous page (opaque)")]
Start = Annotated[
    Instant | None, Query(description="only from this instant on (inclusive; ISO 8601 with a UTC offset)")
]
End = Annotated[Instant | None, Query(description="only before this instant (exclusive)")]
# The gateway's configured node ids (gateway/config.py): anything else names no node.
NODE_ID_PATTERN = r"^[A-Za-z0-9_.-]+$"
NodeId = Annotated[str, Path(min_length=1, max_length=64, pattern=NODE_ID_PATTERN, description="the node's id")]
NodeIdFilter = Annotated[
    str | None, Query(min_length=1, max_length=64, pattern=NODE_ID_PATTERN, description="only this node's")
]
# A site's and a gateway's names as the uplink contract allows them (uplink/contract.py).
SITE_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
SiteFilter = Annotated[str | None, Query(pattern=SITE_NAME_PATTERN, description="only this site's nodes")]
GatewayFilter = Annotated[str | None, Query(pattern=SITE_NAME_PATTERN, description="only this gateway's nodes")]
MeasurementId = Annotated[int, Path(ge=1, le=MAX_ID, description="the measurement's id")]
BaselineId = Annotated[int, Path(ge=1, le=MAX_ID, description="the baseline record's id")]
