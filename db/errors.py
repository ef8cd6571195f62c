"""Typed errors of the storage layer, raised where the fault is found.

The daemon catches :class:`StorageUnavailable` (full disk, I/O error, lock timeout), logs it
and retries later; everything else is a bug or bad input and should surface.
"""
from __future__ import annotations

import sqlite3

from sqlalchemy import exc as sa_exc

# SQLite primary result codes (https://www.sqlite.org/rescode.html); the low byte of an
# extended code is its primary code.
_SQLITE_PERM = 3
_SQLITE_BUSY = 5
_SQLITE_READONLY = 8
_SQLITE_IOERR = 10
_SQLITE_CORRUPT = 11
_SQLITE_FULL = 13
_SQLITE_CANTOPEN = 14
_SQLITE_NOTADB = 26
# PostgreSQL SQLSTATEs (https://www.postgresql.org/docs/current/errcodes-appendix.html).
_PG_DISK_FULL = "53100"
_PG_IO_ERROR = "58030"
_PG_CONNECTION_CLASS = "08"
_PG_SERVER_SHUTDOWN = ("57P01", "57P02", "57P03")  # admin/crash shutdown, cannot connect now


class StorageError(Exception):
    """Base class of every error raised by ``db``."""


class SchemaOutOfDate(StorageError):
    """The database schema is not at the revision this code expects (and we may not upgrade)."""

    def __init__(self, current: str | None, head: str) -> None:
        self.current = current
        self.head = head
        shown = current or "empty (no schema)"
        super().__init__(
            f"database schema is at revision {shown}, this code needs {head}; "
            "migrate it by starting the gateway (open_database(url, upgrade=True)), "
            "or, if the revision is unknown, run a release at least as new as the one that wrote it"
        )


class ForeignDatabase(StorageError):
    """The SQLite file holds another application's tables and no PipeSentry schema: never migrated into."""


class StorageUnavailable(StorageError):
    """Writing is impossible right now for a reason outside the code; retry later."""


class StorageFull(StorageUnavailable):
    """The disk (or the configured database size limit) is full: SQLITE_FULL / SQLSTATE 53100."""


class StorageIOError(StorageUnavailable):
    """The operating system reported an I/O error: SQLITE_IOERR / SQLSTATE 58030."""


class StorageBusy(StorageUnavailable):
    """Another writer held the database lock longer than the busy timeout."""


class StorageConnectionLost(StorageUnavailable):
    """The database server went away (PostgreSQL SQLSTATE class 08)."""


class StorageNotWritable(StorageUnavailable):
    """The file or its directory cannot be opened or written (SQLITE_CANTOPEN, SQLITE_READONLY,
    SQLITE_PERM): a read-only mount, wrong ownership. Retryable: a remount or chown fixes it."""


class DatabaseDamaged(StorageError):
    """The file is not a usable SQLite database: not SQLite at all, truncated, or with corrupt pages
    (SQLITE_NOTADB, SQLITE_CORRUPT, or ``PRAGMA quick_check`` reporting problems).

    Not retryable and never written into: restore it from a backup (docs/storage.md)."""


class CorruptBlob(StorageError):
    """A stored array does not match its checksum, codec, dtype or shape."""


class TracesPruned(StorageError):
    """The raw traces of this measurement were removed by retention; only metadata remains."""


class NotFound(StorageError):
    """A node, measurement or key named by the caller does not exist."""


class BaselineError(StorageError):
    """A measurement cannot serve as this node's baseline (other node, traces pruned, ...)."""


class StateConflict(StorageError):
    """A state change does not start from the node's current state."""


class InvalidCursor(StorageError):
    """A pagination cursor is malformed or was not produced by this module."""


def translate_db_error(error: BaseException) -> StorageUnavailable | DatabaseDamaged | None:
    """Map a driver error to a typed :class:`StorageUnavailable` (retry later) or :class:`DatabaseDamaged`
    (the file is broken), or None if it is neither (a bug: it surfaces)."""
    orig = error.orig if isinstance(error, sa_exc.DBAPIError) else error
    invalidated = isinstance(error, sa_exc.DBAPIError) and error.connection_invalidated
    message = str(orig).splitlines()[0] if str(orig) else type(orig).__name__
    if isinstance(orig, sqlite3.Error):
        code = getattr(orig, "sqlite_errorcode", None)
        primary = code & 0xFF if isinstance(code, int) else None
        if primary == _SQLITE_FULL:
            return StorageFull(f"SQLite: {message}")
        if primary == _SQLITE_IOERR:
            return StorageIOError(f"SQLite: {message}")
        if primary == _SQLITE_BUSY:
            return StorageBusy(f"SQLite: {message}")
        if primary in (_SQLITE_NOTADB, _SQLITE_CORRUPT):
            return DatabaseDamaged(f"SQLite: {message}")
        if primary in (_SQLITE_CANTOPEN, _SQLITE_READONLY, _SQLITE_PERM):
            return StorageNotWritable(f"SQLite: {message}")
        return None
    sqlstate = getattr(orig, "sqlstate", None)
    if sqlstate == _PG_DISK_FULL:
        return StorageFull(f"PostgreSQL: {message}")
    if sqlstate == _PG_IO_ERROR:
        return StorageIOError(f"PostgreSQL: {message}")
    if invalidated or (
        isinstance(sqlstate, str) and (sqlstate.startswith(_PG_CONNECTION_CLASS) or sqlstate in _PG_SERVER_SHUTDOWN)
    ):
        return StorageConnectionLost(f"database connection lost: {message}")
    if isinstance(error, sa_exc.OperationalError) and sqlstate is None:
        # No SQLSTATE: the server was never reached (name not resolved, connection refused, timeout).
        return StorageConnectionLost(f"cannot reach the database server: {message}")
    return None
