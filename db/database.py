"""Opening the database: engine, SQLite set-up, schema check or upgrade, units of work."""
from __future__ import annotations

import logging
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import datetime

from sqlalchemy import create_engine, make_url
from sqlalchemy import exc as sa_exc
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from db import migrate, sqlite_setup
from db.clock import utc_now
from db.errors import (
    DatabaseDamaged,
    ForeignDatabase,
    SchemaOutOfDate,
    StorageBusy,
    StorageError,
    StorageFull,
    StorageUnavailable,
    translate_db_error,
)
from db.uplink_queue import QUEUE_POLICY, QueuePolicy

log = logging.getLogger("pipesentry.storage")

SQLITE_POOL_SIZE = 16  # connections kept open (each is a file handle and a small page cache)
SQLITE_POOL_OVERFLOW = 32
QUICK_CHECK_MAX_ERRORS = 3  # PRAGMA quick_check(N): the first problems found are enough to say it is damaged


@dataclass(frozen=True)
class StorageOutage:
    """Writes have been failing since ``since`` (disk full, I/O error, read-only, server gone)."""

    since: datetime
    reason: str  # the first failure's message
    failed_writes: int
    ended_at: datetime | None = None  # the first write that fitted again


class Database:
    """An engine plus the two kinds of unit of work the project uses.

    ``session()`` is for reading (on SQLite a deferred BEGIN: never blocks, sees one
    snapshot); ``write()`` is for changing data (on SQLite ``BEGIN IMMEDIATE``: takes the
    write lock up front, waiting up to busy_timeout, so a transaction never fails half-way
    on a lock upgrade). Both commit when the block ends normally and roll back on an
    exception. Driver errors that mean "storage unavailable" surface as
    :class:`db.errors.StorageUnavailable` subclasses.

    A database known to be damaged (SQLite reported corrupt pages or "not a database", or
    :meth:`check_integrity` found problems) is never written into again by this object:
    ``write()`` raises :class:`db.errors.DatabaseDamaged` before it begins.
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.is_sqlite = engine.dialect.name == "sqlite"
        self._damage: DatabaseDamaged | None = None
        self._damage_lock = threading.Lock()
        self._outage: StorageOutage | None = None
        self._ended_outages: list[StorageOutage] = []
        self._readers = sessionmaker(engine, expire_on_commit=False)
        writer_engine = (
            engine.execution_options(**{sqlite_setup.BEGIN_MODE_OPTION: sqlite_setup.BEGIN_IMMEDIATE})
            if self.is_sqlite
            else engine
        )
        self._writer_engine = writer_engine
        self._writers = sessionmaker(writer_engine, expire_on_commit=False)

    @property
    def damage(self) -> DatabaseDamaged | None:
        """Why the database is known to be damaged (None: not known to be)."""
        return self._damage

    @contextmanager
    def session(self) -> Iterator[Session]:
        """One read unit of work (a transaction that commits on success)."""
        with self._noting_damage(), _storage_errors(), self._readers.begin() as session:
            yield session

    @contextmanager
    def write(self) -> Iterator[Session]:
        """One write transaction; all of it is committed, or none of it. Refused on a damaged database."""
        damage = self._damage
        if damage is not None:
            raise DatabaseDamaged(f"not written: {damage}")
        try:
            with self._noting_damage(), _storage_errors(), self._writers.begin() as session:
                yield session
        except StorageUnavailable as unavailable:
            self._note_failed_write(unavailable)
            raise
        if self._outage is not None:
            self._note_write_fitted()

    @property
    def storage_outage(self) -> StorageOutage | None:
        """The outage going on now: writes failing since when, why (None: the last write worked)."""
        return self._outage

    def take_ended_outages(self) -> list[StorageOutage]:
        """Outages that ended since the last call (for the gateway's ``storage_unavailable`` event)."""
        with self._damage_lock:
            ended, self._ended_outages = self._ended_outages, []
        return ended

    def _note_failed_write(self, error: StorageUnavailable) -> None:
        if isinstance(error, StorageBusy):
            return  # another writer held the lock: not storage being unavailable
        with self._damage_lock:
            outage = self._outage
            if outage is None:
                self._outage = StorageOutage(since=utc_now(), reason=f"{type(error).__name__}: {error}",
                                             failed_writes=1)
                log.error("storage unavailable: writes fail: %s", error)
            else:
                self._outage = replace(outage, failed_writes=outage.failed_writes + 1)
        if isinstance(error, StorageFull) and self.is_sqlite:
            self.release_wal()

    def _note_write_fitted(self) -> None:
        with self._damage_lock:
            outage, self._outage = self._outage, None
            if outage is None:
                return
            ended = replace(outage, ended_at=utc_now())
            self._ended_outages.append(ended)
        log.warning("storage available again: writes resumed after %d failed (since %s)", ended.failed_writes,
                    ended.since.isoformat(timespec="seconds"))

    def release_wal(self) -> bool:
        """SQLite: ``PRAGMA wal_checkpoint(TRUNCATE)``: the WAL's pages into the database file and the WAL
        file cut to zero, so the space it held is the file system's again. Returns True when it completed
        (it cannot while a reader holds an old snapshot, or while the database file cannot grow)."""
        try:
            with _storage_errors(), self.engine.connect() as connection:
                busy, _log_pages, _done = connection.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)").one()
                connection.commit()
        except StorageError as error:
            log.debug("WAL checkpoint after a full disk did not complete: %s", error)
            return False
        return not busy

    def queue_uplink(self, policy: QueuePolicy | None) -> None:
        """From now on every write of this handle queues what it stores for the uplink under
        ``policy`` (``db.uplink_queue``), or nothing (None), whatever ``uplink_config`` says; the
        gateway calls it at start (and stores its choice there for the other processes:
        ``db.uplink_queue.store_policy``). A handle never told reads ``uplink_config``."""
        self._writers.configure(info={QUEUE_POLICY: policy})

    def schema_revision(self) -> str | None:
        """The Alembic revision the database is at (None if it has no schema)."""
        with self._noting_damage(), _storage_errors(), self.engine.connect() as connection:
            return migrate.current_revision(connection)

    def check_integrity(self) -> DatabaseDamaged | None:
        """SQLite: ``PRAGMA quick_check`` over the whole file (reads every page, O(size); no lock that
        blocks writers in WAL mode). Returns the damage found, and remembers it (no more writes);
        None when the check passes. PostgreSQL checks its own pages: always None."""
        if not self.is_sqlite:
            return None
        with self._noting_damage(), _storage_errors(), self.engine.connect() as connection:
            rows = connection.exec_driver_sql(f"PRAGMA quick_check({QUICK_CHECK_MAX_ERRORS})").scalars().all()
        if [str(r) for r in rows] == ["ok"]:
            return None
        problems = " ".join(" ".join(str(r) for r in rows).split())  # one line: quick_check's rows span several
        found = DatabaseDamaged(f"quick_check found corrupt pages: {problems}")
        self._note_damage(found)
        return found

    def _note_damage(self, damage: DatabaseDamaged) -> None:
        with self._damage_lock:
            if self._damage is None:
                self._damage = damage

    @contextmanager
    def _noting_damage(self) -> Iterator[None]:
        try:
            yield
        except DatabaseDamaged as damage:
            self._note_damage(damage)
            raise

    def dispose(self) -> None:
        """Close all pooled connections (call at shutdown, and after a fork)."""
        self.engine.dispose()


@contextmanager
def _storage_errors() -> Iterator[None]:
    try:
        yield
    except sa_exc.DBAPIError as error:
        mapped = translate_db_error(error)
        if mapped is None:
            raise
        raise mapped from error
    except sqlite3.Error as error:  # raised by the driver outside SQLAlchemy's wrapping (a raw connection)
        mapped = translate_db_error(error)
        if mapped is None:
            raise
        raise mapped from error


def create_db_engine(url: str, *, busy_timeout_ms: int = sqlite_setup.DEFAULT_BUSY_TIMEOUT_MS) -> Engine:
    """An engine for ``url`` with our SQLite set-up installed (no schema work)."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if not parsed.database or parsed.database == ":memory:":
            raise ValueError(
                "SQLite needs a file URL (sqlite:///path/to/file.db); in-memory databases are not supported"
            )
        # Enough pooled connections for the API's worker threads: with SQLAlchemy's default (5 kept,
        # overflow ones closed on return) a busy API reconnects and re-runs the PRAGMAs per request.
        engine = create_engine(parsed, pool_size=SQLITE_POOL_SIZE, max_overflow=SQLITE_POOL_OVERFLOW)
        sqlite_setup.install(engine, busy_timeout_ms)
        return engine
    # pre_ping: the API and gateway outlive PostgreSQL restarts without a failed request.
    return create_engine(parsed, pool_pre_ping=True)


def open_database(
    url: str,
    *,
    upgrade: bool = True,
    busy_timeout_ms: int = sqlite_setup.DEFAULT_BUSY_TIMEOUT_MS,
    check_integrity: bool = False,
) -> Database:
    """Open ``url`` and make sure its schema is at head.

    ``check_integrity``: an existing SQLite file gets ``PRAGMA quick_check`` first, and a damaged
    one raises :class:`DatabaseDamaged` (nothing is migrated or written). Any file that is not a
    usable SQLite database (garbage, truncated, another format) raises it as well.

    With ``upgrade=True`` (the gateway) pending Alembic revisions are applied. With
    ``upgrade=False`` (the API server) nothing is changed and :class:`SchemaOutOfDate` is
    raised unless the database is exactly at head.
    """
    engine = create_db_engine(url, busy_timeout_ms=busy_timeout_ms)
    database = Database(engine)
    try:
        if database.is_sqlite:
            _preflight_sqlite_file(str(engine.url.database), check_integrity=check_integrity)
        found = database.schema_revision()
        if found is not None and found not in migrate.known_revisions():
            # Written by a newer release: neither upgrading nor using it is safe.
            raise SchemaOutOfDate(found, migrate.head_revision())
        if upgrade:
            with _storage_errors():
                migrate.upgrade_to_head(database._writer_engine)
        head = migrate.head_revision()
        current = database.schema_revision()
        if current != head:
            raise SchemaOutOfDate(current, head)
    except BaseException:
        engine.dispose()
        raise
    return database


def _preflight_sqlite_file(path: str, *, check_integrity: bool) -> None:
    """Look at an existing SQLite file read-only before our connections change anything (they switch it
    to WAL): not SQLite or truncated is :class:`DatabaseDamaged`, another application's tables without
    our schema stamp :class:`ForeignDatabase`; with ``check_integrity`` also ``PRAGMA quick_check``."""
    try:
        if os.path.getsize(path) == 0:
            return  # a new file: nothing to damage
    except OSError:
        return  # not there yet: the gateway creates it
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as error:
        raise _mapped(error) from error
    try:
        tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if check_integrity:
            rows = [str(r[0]) for r in connection.execute(f"PRAGMA quick_check({QUICK_CHECK_MAX_ERRORS})")]
            if rows != ["ok"]:
                raise DatabaseDamaged(f"quick_check found corrupt pages: {' '.join(' '.join(rows).split())}")
    except sqlite3.Error as error:
        raise _mapped(error) from error
    finally:
        connection.close()
    if tables and "alembic_version" not in tables:
        shown = ", ".join(sorted(tables)[:5]) + (", ..." if len(tables) > 5 else "")
        raise ForeignDatabase(
            f"the file holds {len(tables)} table(s) of something else ({shown}) and no PipeSentry schema: "
            "not touched; point the database URL at a new file"
        )


def _mapped(error: sqlite3.Error) -> Exception:
    mapped = translate_db_error(error)
    return mapped if mapped is not None else error
