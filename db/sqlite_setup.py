"""Connection set-up for SQLite files: pragmas, and who emits BEGIN.

Why each value was chosen is written down in docs/storage.md ("Pragmas").
"""
from __future__ import annotations

import sqlite3
from typing import Any

from sqlalchemy import event
from sqlalchemy.engine import Connection, Engine

from db.errors import StorageError

# Raw traces are ~100 kB blobs. A 16 KiB page keeps one in a chain of ~7 overflow pages
# instead of ~25 at the 4 KiB default (fewer page reads and WAL frames per blob), while the
# small rows (nodes, detections) still cost only one page per change.
PAGE_SIZE_BYTES = 16384
# FULL: the WAL is fsynced at every COMMIT, so a committed row survives power loss.
# One fsync per measurement is nothing at our write rate (see docs/storage.md).
SYNCHRONOUS = "FULL"
DEFAULT_BUSY_TIMEOUT_MS = 5000
# The WAL is checkpointed into the database file every this many pages (2 MiB at 16 KiB pages, about
# 15 measurements) instead of SQLite's 1000 (16 MiB): the space it holds on a full disk stays small.
WAL_AUTOCHECKPOINT_PAGES = 128
# After a checkpoint the WAL file is truncated back to this size, so a burst of writes does not
# keep its disk space (a full disk: the space a write needs is not held by an old WAL).
JOURNAL_SIZE_LIMIT_BYTES = 4 * 1024 * 1024

BEGIN_MODE_OPTION = "pipesentry_sqlite_begin"  # execution option read by the begin hook
BEGIN_DEFERRED = "DEFERRED"
BEGIN_IMMEDIATE = "IMMEDIATE"


class SQLiteSetupError(StorageError):
    """The SQLite file cannot be put into the mode we rely on (e.g. WAL is unsupported)."""


def _scalar(cursor: sqlite3.Cursor, sql: str) -> Any:
    row = cursor.execute(sql).fetchone()
    return None if row is None else row[0]


def configure_connection(dbapi_connection: sqlite3.Connection, busy_timeout_ms: int) -> None:
    """Apply our pragmas to a new DB-API connection (file-level ones only on an empty file)."""
    # sqlite3 must not emit BEGIN itself (it would skip it for SELECT and DDL); the engine's
    # "begin" hook does it instead: SQLAlchemy's documented recipe for pysqlite.
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    try:
        cursor.execute(f"PRAGMA busy_timeout = {int(busy_timeout_ms)}")
        if _scalar(cursor, "PRAGMA page_count") == 0:
            # Only possible before the first page is written: page size is fixed once the
            # file exists in WAL mode, and auto_vacuum needs a full VACUUM once tables exist.
            cursor.execute(f"PRAGMA page_size = {PAGE_SIZE_BYTES}")
            cursor.execute("PRAGMA auto_vacuum = INCREMENTAL")
        mode = _scalar(cursor, "PRAGMA journal_mode = WAL")
        if mode != "wal":
            # synchronous=FULL is safe in any journal mode, but concurrent readers during
            # writes (the API while the gateway stores) need WAL: refuse rather than degrade.
            raise SQLiteSetupError(f"SQLite refused WAL journal mode (got {mode!r}); is this a network filesystem?")
        cursor.execute(f"PRAGMA synchronous = {SYNCHRONOUS}")
        cursor.execute("PRAGMA foreign_keys = ON")
        cursor.execute(f"PRAGMA journal_size_limit = {JOURNAL_SIZE_LIMIT_BYTES}")
        cursor.execute(f"PRAGMA wal_autocheckpoint = {WAL_AUTOCHECKPOINT_PAGES}")
    finally:
        cursor.close()


def install(engine: Engine, busy_timeout_ms: int) -> None:
    """Hook pragmas and BEGIN handling into ``engine`` (a ``sqlite+pysqlite`` file engine)."""

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: sqlite3.Connection, _record: Any) -> None:
        configure_connection(dbapi_connection, busy_timeout_ms)

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        mode = connection.get_execution_options().get(BEGIN_MODE_OPTION, BEGIN_DEFERRED)
        if mode not in (BEGIN_DEFERRED, BEGIN_IMMEDIATE):
            raise ValueError(f"unknown SQLite BEGIN mode {mode!r}")
        connection.exec_driver_sql(f"BEGIN {mode}")
