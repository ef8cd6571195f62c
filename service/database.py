"""The API's handle on the gateway's database: opened lazily, never migrated, readiness checked.

The API starts even when the database is missing or at another schema revision, so that
``/healthz`` answers and ``/readyz`` can say why it is not ready; every data request then
gets a 503 problem until the gateway has created or migrated the database.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

from sqlalchemy import make_url

from db.database import Database, open_database
from db.errors import DatabaseDamaged, ForeignDatabase, SchemaOutOfDate, StorageError, StorageFull, StorageUnavailable
from db.migrate import head_revision

log = logging.getLogger("pipesentry.api")

REFUSED_RETRY_S = 30.0  # a damaged or foreign file is looked at again after this long (not on every request)
DEFAULT_INTEGRITY_CHECK_EVERY_S = 6 * 3600.0
DEFAULT_MIN_FREE_BYTES = 8 * 1024 * 1024


class DatabaseMissing(StorageUnavailable):
    """The SQLite file does not exist yet (the gateway creates it); the API never creates it."""


class DatabaseGate:
    """Opens the database on first use with ``upgrade=False`` and keeps it open.

    A SQLite file is ``quick_check``-ed when opened and again every ``integrity_check_every_s`` (in a
    background thread started by a readiness probe); a damaged or foreign file is refused, and
    looked at again only after ``REFUSED_RETRY_S``.
    """

    def __init__(
        self,
        url: str,
        *,
        busy_timeout_ms: int,
        integrity_check_every_s: float = DEFAULT_INTEGRITY_CHECK_EVERY_S,
        min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
    ) -> None:
        self.url = url
        self.busy_timeout_ms = busy_timeout_ms
        self.integrity_check_every_s = integrity_check_every_s
        self.min_free_bytes = min_free_bytes
        self._database: Database | None = None
        self._refused: tuple[StorageError, float] | None = None
        self._checked_at = 0.0
        self._checking: threading.Thread | None = None
        self._lock = threading.Lock()

    def get(self) -> Database:
        """The open database; raises :class:`SchemaOutOfDate`, :class:`DatabaseDamaged`,
        :class:`ForeignDatabase` or :class:`StorageUnavailable`."""
        database = self._database
        if database is not None:
            return database
        with self._lock:
            if self._database is None:
                refused = self._refused
                if refused is not None and time.monotonic() - refused[1] < REFUSED_RETRY_S:
                    raise refused[0]
                self._refuse_missing_sqlite_file()
                try:
                    self._database = open_database(self.url, upgrade=False, busy_timeout_ms=self.busy_timeout_ms,
                                                   check_integrity=True)
                except (DatabaseDamaged, ForeignDatabase) as error:
                    self._refused = (error, time.monotonic())
                    log.error("database refused: %s: %s", type(error).__name__, error)
                    raise
                self._refused = None
                self._checked_at = time.monotonic()
            return self._database

    def opened(self) -> Database | None:
        """The database if it is open already (never blocks), else None."""
        return self._database

    def check_ready(self) -> str:
        """The schema revision if the database answers and is at this release's head; raises otherwise."""
        database = self.get()
        self._schedule_integrity_check(database)
        if database.damage is not None:
            raise database.damage
        revision = database.schema_revision()
        head = head_revision()
        if revision != head:
            raise SchemaOutOfDate(revision, head)
        self._refuse_full_filesystem()
        return revision

    def _schedule_integrity_check(self, database: Database) -> None:
        """Start a background ``quick_check`` when the last one is older than the interval (never two at once)."""
        if not database.is_sqlite or database.damage is not None:
            return
        with self._lock:
            running = self._checking is not None and self._checking.is_alive()
            if running or time.monotonic() - self._checked_at < self.integrity_check_every_s:
                return
            self._checked_at = time.monotonic()
            self._checking = threading.Thread(target=self._integrity_check, args=(database,),
                                              name="integrity-check", daemon=True)
            self._checking.start()

    @staticmethod
    def _integrity_check(database: Database) -> None:
        try:
            damage = database.check_integrity()
        except StorageError as error:  # unreadable now: the next probe tries again
            log.warning("integrity check not done: %s", error)
            return
        if damage is not None:
            log.error("database damaged: %s", damage)

    def _refuse_full_filesystem(self) -> None:
        """SQLite: too little space left for the gateway's next measurement is not ready (it cannot store)."""
        url = make_url(self.url)
        if url.get_backend_name() != "sqlite" or not url.database:
            return
        try:
            stats = os.statvfs(Path(url.database).parent)
        except OSError as error:
            raise StorageUnavailable(f"cannot look at the database's filesystem: {error}") from None
        free = stats.f_bavail * stats.f_frsize
        if free < self.min_free_bytes:
            raise StorageFull(
                f"storage_unavailable: {free} bytes free on the database's filesystem, below {self.min_free_bytes} "
                "(min_free_bytes): new measurements cannot be stored; free space there"
            )

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
