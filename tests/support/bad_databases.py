"""Broken database files as an operator may find them: garbage, a truncated copy, another format, another
application's SQLite file, and a PipeSentry database whose pages were damaged on disk."""
from __future__ import annotations

import gzip
import sqlite3
from collections.abc import Callable
from pathlib import Path

from db.database import open_database
from tests.support.db_fixtures import T0, minutes, store_sample

PAGE_SIZE = 16384  # db/sqlite_setup.py's page size
SAMPLES = 6


def good_database(path: Path, samples: int = SAMPLES) -> Path:
    """A PipeSentry database at head with ``samples`` measurements, checkpointed into the main file."""
    database = open_database(f"sqlite:///{path}")
    try:
        with database.write() as session:
            for i in range(samples):
                store_sample(session, acquired_at=T0 + minutes(i), seed=i)
    finally:
        database.dispose()
    with sqlite3.connect(path) as connection:
        connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return path


def garbage(path: Path) -> None:
    path.write_bytes(b"this is not a database, only bytes. " * 2000)


def truncated(path: Path) -> None:
    good = good_database(path.with_name("whole.db"))
    data = good.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def other_format(path: Path) -> None:
    """A gzip stream where the database should be (a backup restored without unpacking it)."""
    path.write_bytes(gzip.compress(b"SQLite format 3\x00" + bytes(PAGE_SIZE * 2)))


def foreign_sqlite(path: Path) -> None:
    """A valid SQLite file of another application: its tables, no PipeSentry schema."""
    with sqlite3.connect(path) as connection:
        connection.execute("CREATE TABLE invoices (id INTEGER PRIMARY KEY, total REAL)")
        connection.execute("INSERT INTO invoices (total) VALUES (12.5)")


def corrupt_pages(path: Path) -> None:
    """A PipeSentry database whose measurements b-tree root page was overwritten on disk."""
    good_database(path)
    with sqlite3.connect(path) as connection:
        root = connection.execute("SELECT rootpage FROM sqlite_master WHERE name = 'measurements'").fetchone()[0]
    with path.open("r+b") as file:
        file.seek((root - 1) * PAGE_SIZE + 8)
        file.write(b"\xa5" * (PAGE_SIZE - 8))


BAD_FILES: dict[str, Callable[[Path], None]] = {
    "garbage": garbage,
    "truncated": truncated,
    "other-format": other_format,
    "foreign-sqlite": foreign_sqlite,
    "corrupt-pages": corrupt_pages,
}
