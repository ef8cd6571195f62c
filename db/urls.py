"""Database URLs checked before anything is opened: a typo is one clear line, never a traceback later.

Everything that takes a database URL (the gateway config, the API settings, ``pipesentry apikey``,
``python -m db``) runs it through :func:`check_database_url` first. It opens nothing: it parses
the URL, loads the SQLAlchemy dialect and imports its driver, and for SQLite looks at the
file's directory.
"""
from __future__ import annotations

import difflib
import os
from pathlib import Path

from sqlalchemy import make_url
from sqlalchemy.engine import URL
from sqlalchemy.exc import ArgumentError, NoSuchModuleError

from db.errors import StorageError

SUPPORTED_BACKENDS = ("sqlite", "postgresql")
EXAMPLES = "sqlite:////var/lib/pipesentry/pipesentry.db or postgresql+psycopg://user@host/dbname"


class DatabaseUrlError(StorageError, ValueError):
    """The database URL cannot work: unparseable, an unknown or unsupported database, a missing driver
    or SQLite directory. The message says what is wrong and what a good URL looks like."""


def check_database_url(url: str, *, writable: bool = False) -> URL:
    """The parsed URL if a start could use it; raise :class:`DatabaseUrlError` otherwise.

    ``writable``: the caller creates the SQLite file and its WAL side files, so the file's
    directory must be writable too (the gateway), not only exist (the API, the CLI).
    """
    try:
        parsed = make_url(url)
    except ArgumentError:
        raise DatabaseUrlError(f"not a database URL: {_shown(url)!r} (expected e.g. {EXAMPLES})") from None
    backend = parsed.get_backend_name()
    if backend not in SUPPORTED_BACKENDS:
        close = difflib.get_close_matches(backend, SUPPORTED_BACKENDS, n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise DatabaseUrlError(
            f"unsupported database {backend!r} in {_shown(url)!r}: {hint}PipeSentry stores in SQLite or PostgreSQL "
            f"(e.g. {EXAMPLES})"
        )
    try:
        dialect = parsed.get_dialect()
        dialect.import_dbapi()
    except (NoSuchModuleError, ImportError) as exc:
        raise DatabaseUrlError(
            f"no driver {parsed.drivername!r} for {_shown(url)!r} ({exc}); use sqlite:/// or postgresql+psycopg://"
        ) from None
    if getattr(dialect, "is_async", False):
        raise DatabaseUrlError(f"{parsed.drivername!r} is an asyncio driver; use sqlite:/// or postgresql+psycopg://")
    if backend == "sqlite":
        _check_sqlite_file(parsed, writable=writable)
    return parsed


def safe_database_url(url: str) -> str:
    """The URL for logs and messages: its password hidden (or a placeholder if it does not parse)."""
    return _shown(url)


def _check_sqlite_file(parsed: URL, *, writable: bool) -> None:
    database = parsed.database
    if not database or database == ":memory:" or database.startswith("file::memory:"):
        raise DatabaseUrlError(
            "SQLite needs a file (sqlite:///relative/path.db or sqlite:////absolute/path.db); "
            "an in-memory database would lose every measurement at exit and cannot be shared with the API"
        )
    directory = Path(database).expanduser().parent
    if not directory.is_dir():
        raise DatabaseUrlError(f"the directory of the SQLite file {database} does not exist: create {directory}")
    if writable and not os.access(directory, os.W_OK | os.X_OK):
        raise DatabaseUrlError(
            f"cannot write in {directory} (the SQLite file {Path(database).name} and its -wal/-shm files go there)"
        )


def _shown(url: str) -> str:
    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return url if "@" not in url else "<unparseable url>"
