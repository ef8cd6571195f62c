"""Specification of bad database files: every kind is refused by name before anything is written,
and a database found damaged while open is never written into again."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from db.database import open_database
from db.errors import DatabaseDamaged, ForeignDatabase, StorageNotWritable, translate_db_error
from tests.support.bad_databases import BAD_FILES, corrupt_pages, good_database
from tests.support.db_fixtures import T0, minutes, store_sample

EXPECTED = {
    "garbage": (DatabaseDamaged, "file is not a database"),
    "truncated": (DatabaseDamaged, "malformed"),
    "other-format": (DatabaseDamaged, "file is not a database"),
    "foreign-sqlite": (ForeignDatabase, "invoices"),
    "corrupt-pages": (DatabaseDamaged, "quick_check found corrupt pages"),
}


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_a_bad_file_is_refused_with_a_one_line_reason_and_left_as_it_was(kind: str, tmp_path: Path):
    path = tmp_path / f"{kind}.db"
    BAD_FILES[kind](path)
    before = path.read_bytes()
    error_type, words = EXPECTED[kind]
    with pytest.raises(error_type, match=words) as refused:
        open_database(f"sqlite:///{path}", upgrade=True, check_integrity=True)
    assert "\n" not in str(refused.value)
    assert path.read_bytes() == before  # not migrated, not "repaired", not written at all


def test_a_new_empty_file_is_not_damaged(tmp_path: Path):
    path = tmp_path / "new.db"
    path.touch()
    database = open_database(f"sqlite:///{path}", check_integrity=True)
    try:
        assert database.check_integrity() is None and database.damage is None
    finally:
        database.dispose()


def test_damage_found_while_open_stops_every_later_write(tmp_path: Path):
    path = good_database(tmp_path / "live.db")
    database = open_database(f"sqlite:///{path}", check_integrity=True)
    try:
        assert database.check_integrity() is None
        corrupt_pages(path)  # the disk goes bad under a running gateway
        found = database.check_integrity()
        assert found is not None and database.damage is found
        size = path.stat().st_size
        with pytest.raises(DatabaseDamaged, match="not written"):
            with database.write() as session:
                store_sample(session, acquired_at=T0 + minutes(99), seed=99)
        assert path.stat().st_size == size
    finally:
        database.dispose()


def test_a_read_that_meets_corrupt_pages_marks_the_database_damaged(tmp_path: Path):
    path = good_database(tmp_path / "live.db")
    database = open_database(f"sqlite:///{path}")
    try:
        database.dispose()  # no page of the file stays cached
        corrupt_pages(path)
        with pytest.raises(DatabaseDamaged):
            with database.session() as session:
                session.connection().exec_driver_sql("SELECT count(*), sum(length(traces_blob)) FROM measurements").all()
        assert database.damage is not None
        with pytest.raises(DatabaseDamaged, match="not written"):
            with database.write():
                pass
    finally:
        database.dispose()


def test_sqlite_codes_of_bad_files_map_to_typed_errors():
    def error(code: int) -> sqlite3.DatabaseError:
        made = sqlite3.DatabaseError("x")
        made.sqlite_errorcode = code
        return made

    assert isinstance(translate_db_error(error(26)), DatabaseDamaged)  # SQLITE_NOTADB
    assert isinstance(translate_db_error(error(11)), DatabaseDamaged)  # SQLITE_CORRUPT
    assert isinstance(translate_db_error(error(14)), StorageNotWritable)  # SQLITE_CANTOPEN
    assert isinstance(translate_db_error(error(8 | (3 << 8))), StorageNotWritable)  # SQLITE_READONLY_ROLLBACK
