"""Specification of running out of space: a typed, retryable error, no damage, writes resume."""
from __future__ import annotations

import sqlite3

import numpy as np
import psycopg
import psycopg.errors
import pytest
from sqlalchemy import event, func, select, text

from db.database import open_database
from db.errors import StorageConnectionLost, StorageFull, StorageIOError, StorageUnavailable, translate_db_error
from db.measurements import get_measurement, load_traces
from db.models import MeasurementRow
from tests.support.db_fixtures import PG_ADMIN_CONNINFO, T0, minutes, sample_codes, store_sample

MAX_ATTEMPTS = 50


def _integrity(database) -> str:
    with database.session() as session:
        return session.execute(text("PRAGMA integrity_check")).scalar_one()


def test_full_disk_raises_storage_full_keeps_data_intact_and_writes_resume(sqlite_url):
    database = open_database(sqlite_url)
    limit: dict[str, int | None] = {"pages": None}

    # The real SQLite size limit stands in for a full disk: SQLite raises the same
    # SQLITE_FULL ("database or disk is full") for both.
    @event.listens_for(database.engine, "checkout")
    def _apply_limit(dbapi_connection, _record, _proxy):
        pages = limit["pages"] if limit["pages"] is not None else 2**31
        dbapi_connection.execute(f"PRAGMA max_page_count = {pages}")

    try:
        with database.write() as session:
            kept = [store_sample(session, acquired_at=T0 + minutes(i), seed=i).id for i in range(3)]
        with database.session() as session:
            limit["pages"] = session.execute(text("PRAGMA page_count")).scalar_one() + 2

        with pytest.raises(StorageFull, match="full"):
            for attempt in range(MAX_ATTEMPTS):
                with database.write() as session:
                    store_sample(session, acquired_at=T0 + minutes(10 + attempt), seed=10 + attempt)
        assert _integrity(database) == "ok"

        limit["pages"] = None  # space comes back; the same Database carries on
        with database.write() as session:
            resumed = store_sample(session, acquired_at=T0 + minutes(100), seed=100).id
        assert _integrity(database) == "ok"
        with database.session() as session:
            stored = session.scalars(select(MeasurementRow).order_by(MeasurementRow.id)).all()
            assert kept[0] == stored[0].id and resumed == stored[-1].id
            for row in stored:  # every row that exists is whole
                np.testing.assert_array_equal(load_traces(row), sample_codes(row.node_measurement_id))
            np.testing.assert_array_equal(load_traces(get_measurement(session, resumed)), sample_codes(100))
    finally:
        database.dispose()


def test_storage_full_is_a_retryable_storage_unavailable():
    assert issubclass(StorageFull, StorageUnavailable)
    assert issubclass(StorageIOError, StorageUnavailable)


def test_driver_errors_map_to_typed_storage_errors():
    full = sqlite3.OperationalError("database or disk is full")
    full.sqlite_errorcode = 13  # SQLITE_FULL
    io_write = sqlite3.OperationalError("disk I/O error")
    io_write.sqlite_errorcode = 10 | (3 << 8)  # SQLITE_IOERR_WRITE: extended codes map by primary code
    constraint = sqlite3.IntegrityError("UNIQUE constraint failed")
    constraint.sqlite_errorcode = 2067  # SQLITE_CONSTRAINT_UNIQUE: a bug, not the disk
    assert isinstance(translate_db_error(full), StorageFull)
    assert isinstance(translate_db_error(io_write), StorageIOError)
    assert translate_db_error(constraint) is None
    assert isinstance(translate_db_error(psycopg.errors.DiskFull("no space left")), StorageFull)
    assert isinstance(translate_db_error(psycopg.errors.IoError("read failed")), StorageIOError)
    assert isinstance(translate_db_error(psycopg.errors.AdminShutdown("bye")), StorageConnectionLost)
    assert isinstance(translate_db_error(psycopg.errors.ConnectionFailure("gone")), StorageConnectionLost)
    assert translate_db_error(psycopg.errors.UniqueViolation("dup")) is None


def test_real_sqlite_full_error_carries_the_code_we_map(tmp_path):
    connection = sqlite3.connect(tmp_path / "tiny.db", isolation_level=None)
    connection.execute("CREATE TABLE t (b BLOB)")
    pages = connection.execute("PRAGMA page_count").fetchone()[0]
    connection.execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(sqlite3.OperationalError) as raised:
        connection.execute("INSERT INTO t VALUES (zeroblob(100000))")
    connection.close()
    assert isinstance(translate_db_error(raised.value), StorageFull)


def test_postgres_backend_killed_mid_transaction_is_connection_lost_and_the_next_write_works(postgres_db):
    with pytest.raises(StorageConnectionLost):
        with postgres_db.write() as session:
            pid = session.execute(text("SELECT pg_backend_pid()")).scalar_one()
            with psycopg.connect(PG_ADMIN_CONNINFO, autocommit=True) as admin:
                admin.execute("SELECT pg_terminate_backend(%s)", (pid,))
            session.execute(text("SELECT 1"))
    with postgres_db.write() as session:
        store_sample(session)
    with postgres_db.session() as session:
        assert session.scalar(select(func.count()).select_from(MeasurementRow)) == 1
