"""Path and query parameters shared by the routes: paging, time ranges, ids."""
from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query
from pydantic import AwareDatetime

from db.pagination import MAX_PAGE_SIZE
from service.schemas import MAX_ID

DEFAULT_LIMIT = 50

Limit = Annotated[int, Query(ge=1, le=MAX_PAGE_SIZE, description="page size")]
Cursor = Annotated[str | None, Query(max_length=512, description="next_cursor of the previous page (opaque)")]
Start = Annotated[
    AwareDatetime | None, Query(description="only from this instant on (inclusive; ISO 8601 with a UTC offset)")
]
End = Annotated[AwareDatetime | None, Query(description="only before this instant (exclusive)")]
NodeId = Annotated[str, Path(min_length=1, max_length=64, description="the node's id")]
MeasurementId = Annotated[int, Path(ge=1, le=MAX_ID, description="the measurement's id")]
BaselineId = Annotated[int, Path(ge=1, le=MAX_ID, description="the baseline record's id")]
