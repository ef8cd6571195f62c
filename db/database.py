"""Opening the database: engine, SQLite set-up, schema check or upgrade, units of work."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import create_engine, make_url
from sqlalchemy import exc as sa_exc
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from db import migrate, sqlite_setup
from db.errors import SchemaOutOfDate, translate_db_error

SQLITE_POOL_SIZE = 16  # connections kept open (each is a file handle and a small page cache)
SQLITE_POOL_OVERFLOW = 32


class Database:
    """An engine plus the two kinds of unit of work the project uses.

    ``session()`` is for reading (on SQLite a deferred BEGIN: never blocks, sees one
    snapshot); ``write()`` is for changing data (on SQLite ``BEGIN IMMEDIATE``: takes the
    write lock up front, waiting up to busy_timeout, so a transaction never fails half-way
    on a lock upgrade). Both commit when the block ends normally and roll back on an
    exception. Driver errors that mean "storage unavailable" surface as
    :class:`db.errors.StorageUnavailable` subclasses.
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.is_sqlite = engine.dialect.name == "sqlite"
        self._readers = sessionmaker(engine, expire_on_commit=False)
        writer_engine = (
            engine.execution_options(**{sqlite_setup.BEGIN_MODE_OPTION: sqlite_setup.BEGIN_IMMEDIATE})
            if self.is_sqlite
            else engine
        )
        self._writer_engine = writer_engine
        self._writers = sessionmaker(writer_engine, expire_on_commit=False)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """One read unit of work (a transaction that commits on success)."""
        with _storage_errors(), self._readers.begin() as session:
            yield session

    @contextmanager
    def write(self) -> Iterator[Session]:
        """One write transaction; all of it is committed, or none of it."""
        with _storage_errors(), self._writers.begin() as session:
            yield session

    def schema_revision(self) -> str | None:
        """The Alembic revision the database is at (None if it has no schema)."""
        with _storage_errors(), self.engine.connect() as connection:
            return migrate.current_revision(connection)

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
) -> Database:
    """Open ``url`` and make sure its schema is at head.

    With ``upgrade=True`` (the gateway) pending Alembic revisions are applied. With
    ``upgrade=False`` (the API server) nothing is changed and :class:`SchemaOutOfDate` is
    raised unless the database is exactly at head.
    """
    engine = create_db_engine(url, busy_timeout_ms=busy_timeout_ms)
    database = Database(engine)
    try:
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
