"""The API's handle on the gateway's database: opened lazily, never migrated, readiness checked.

The API starts even when the database is missing or at another schema revision, so that
``/healthz`` answers and ``/readyz`` can say why it is not ready; every data request then
gets a 503 problem until the gateway has created or migrated the database.
"""
from __future__ import annotations

import threading
from pathlib import Path

from sqlalchemy import make_url

from db.database import Database, open_database
from db.errors import SchemaOutOfDate, StorageUnavailable
from db.migrate import head_revision


class DatabaseMissing(StorageUnavailable):
    """The SQLite file does not exist yet (the gateway creates it); the API never creates it."""


class DatabaseGate:
    """Opens the database on first use with ``upgrade=False`` and keeps it open."""

    def __init__(self, url: str, *, busy_timeout_ms: int) -> None:
        self.url = url
        self.busy_timeout_ms = busy_timeout_ms
        self._database: Database | None = None
        self._lock = threading.Lock()

    def get(self) -> Database:
        """The open database; raises :class:`SchemaOutOfDate` or :class:`StorageUnavailable`."""
        database = self._database
        if database is not None:
            return database
        with self._lock:
            if self._database is None:
                self._refuse_missing_sqlite_file()
                self._database = open_database(self.url, upgrade=False, busy_timeout_ms=self.busy_timeout_ms)
            return self._database

    def opened(self) -> Database | None:
        """The database if it is open already (never blocks), else None."""
        return self._database

    def check_ready(self) -> str:
        """The schema revision if the database answers and is at this release's head; raises otherwise."""
        revision = self.get().schema_revision()
        head = head_revision()
        if revision != head:
            raise SchemaOutOfDate(revision, head)
        return revision

    def dispose(self) -> None:
        with self._lock:
            if self._database is not None:
                self._database.dispose()
                self._database = None

    def _refuse_missing_sqlite_file(self) -> None:
        url = make_url(self.url)
        if url.get_backend_name() == "sqlite" and url.database and not Path(url.database).exists():
            # The path stays on the server: /readyz and 401s answer callers without a key.
            raise DatabaseMissing("no database file yet (the gateway creates it on its first start)")
