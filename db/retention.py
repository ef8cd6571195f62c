"""Retention: drop old raw traces in bounded batches, keep everything derived from them.

Measurement rows, DI maps, detections and state changes stay forever; only
``measurements.traces_blob`` is cleared (with ``traces_pruned_at`` set). A measurement that
is, was, or was recorded as a baseline is never pruned: every stored DI map must remain
reproducible from its baseline's traces. Nor is a measurement whose traces an uplink record
still has to carry to the central PipeSentry (``db.uplink_queue``): they are pruned once the
centre has them.
"""
from __future__ import annotations

import sqlite3
from collections.abc import Callable
from contextlib import AbstractContextManager
from datetime import datetime, timedelta

from sqlalchemy import select, update
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.orm import Session

from db.clock import utc_now
from db.errors import translate_db_error
from db.models import BaselineRow, MeasurementKind, MeasurementRow
from db.uplink_queue import unsent_traces

SessionFactory = Callable[[], AbstractContextManager[Session]]
DEFAULT_MAX_BATCHES = 10_000
VACUUM_PAGES_PER_STEP = 256  # 4 MiB at 16 KiB pages: a short write lock per step
MAX_VACUUM_STEPS = 10_000


def prune_traces(
    session_factory: SessionFactory,
    older_than: timedelta,
    batch_size: int,
    *,
    now: datetime | None = None,
    max_batches: int = DEFAULT_MAX_BATCHES,
) -> int:
    """Clear raw traces acquired before ``now - older_than``; returns how many were pruned.

    ``session_factory`` is ``Database.write``: each batch of at most ``batch_size`` rows is
    its own short transaction, so the gateway's writes interleave with a long prune. On
    SQLite the freed pages are then returned to the file system with
    ``PRAGMA incremental_vacuum`` in bounded steps.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if older_than < timedelta(0):
        raise ValueError(f"older_than must not be negative, got {older_than}")
    now = now or utc_now()
    cutoff = now - older_than
    ever_baseline = select(BaselineRow.measurement_id)
    pruned = 0
    engine: Engine | Connection | None = None
    for _ in range(max_batches):
        with session_factory() as session:
            engine = session.get_bind()
            ids = session.scalars(
                select(MeasurementRow.id)
                .where(
                    MeasurementRow.acquired_at < cutoff,
                    MeasurementRow.traces_pruned_at.is_(None),
                    MeasurementRow.kind != MeasurementKind.BASELINE,
                    MeasurementRow.id.not_in(ever_baseline),
                    MeasurementRow.id.not_in(unsent_traces()),
                )
                .order_by(MeasurementRow.acquired_at, MeasurementRow.id)
                .limit(batch_size)
            ).all()
            if ids:
                session.execute(
                    update(MeasurementRow)
                    .where(MeasurementRow.id.in_(ids))
                    .values(traces_blob=None, traces_pruned_at=now)
                    .execution_options(synchronize_session=False)
                )
        pruned += len(ids)
        if len(ids) < batch_size:
            break
    if pruned and engine is not None and engine.dialect.name == "sqlite":
        reclaim_free_pages(engine if isinstance(engine, Engine) else engine.engine)
    return pruned


def reclaim_free_pages(
    engine: Engine, *, pages_per_step: int = VACUUM_PAGES_PER_STEP, max_steps: int = MAX_VACUUM_STEPS
) -> int:
    """SQLite: give free pages back to the file system, ``pages_per_step`` per transaction.

    Returns the number of pages still free afterwards (0 unless ``max_steps`` ran out).
    """
    remaining = 0
    for _ in range(max_steps):
        pooled = engine.raw_connection()
        try:
            connection = pooled.driver_connection
            assert connection is not None  # a pooled connection always has its DBAPI connection
            # sqlite3's execute() steps a statement once, which frees only one page;
            # executescript() runs it to completion, in its own autocommit transaction
            # (our connections have isolation_level=None and none is open between uses).
            connection.executescript(f"PRAGMA incremental_vacuum({int(pages_per_step)});")
            remaining = int(connection.execute("PRAGMA freelist_count").fetchone()[0])
        except sqlite3.Error as error:
            mapped = translate_db_error(error)
            if mapped is None:
                raise
            raise mapped from error
        finally:
            pooled.close()
        if remaining == 0:
            break
    return remaining
