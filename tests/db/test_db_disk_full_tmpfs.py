"""Specification of a full disk, on a real size-limited file system (a tmpfs the test mounts): the WAL
never holds more than its bound, writes resume with the first one that fits after space is freed, and
nothing committed is lost."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select, text

from db.database import open_database
from db.errors import StorageFull
from db.measurements import load_traces
from db.models import MeasurementRow
from db.sqlite_setup import JOURNAL_SIZE_LIMIT_BYTES
from tests.support.db_fixtures import T0, minutes, sample_codes, store_sample
from tests.support.small_filesystem import MIB, fill, shrink, small_filesystem

MAX_WRITES = 2000  # far more than 12 MiB of samples: the loop ends at the first full disk


def test_a_full_disk_keeps_the_wal_bounded_and_the_first_write_after_freeing_space_fits(tmp_path: Path):
    with small_filesystem(tmp_path / "fs", size_mib=24) as fs:
        database = open_database(f"sqlite:///{fs / 'pipesentry.db'}")
        try:
            filler = fill(fs, leave_bytes=12 * MIB)
            stored: list[int] = []
            with pytest.raises(StorageFull):
                for i in range(MAX_WRITES):
                    with database.write() as session:
                        row_id = store_sample(session, acquired_at=T0 + minutes(i), seed=i).id
                    stored.append(row_id)  # committed (a commit that fails on the full disk raises above)
            outage = database.storage_outage
            assert outage is not None and "full" in outage.reason and outage.failed_writes == 1
            wal = fs / "pipesentry.db-wal"
            # Before: the WAL grew to hold every page written since the start (SQLite checkpoints at 16 MiB).
            assert not wal.exists() or wal.stat().st_size <= JOURNAL_SIZE_LIMIT_BYTES, wal.stat().st_size

            with pytest.raises(StorageFull):  # still full: the same outage goes on
                with database.write() as session:
                    store_sample(session, acquired_at=T0 + minutes(5000), seed=5000)
            assert database.storage_outage is not None and database.storage_outage.failed_writes == 2

            shrink(filler, 1 * MIB)  # an operator frees 1 MiB: about ten measurements' worth
            with database.write() as session:
                resumed = store_sample(session, acquired_at=T0 + minutes(6000), seed=6000).id
            assert database.storage_outage is None
            [ended] = database.take_ended_outages()
            assert ended.failed_writes == 2 and ended.ended_at is not None

            with database.session() as session:
                assert session.execute(text("PRAGMA integrity_check")).scalar_one() == "ok"
                rows = session.scalars(select(MeasurementRow).order_by(MeasurementRow.id)).all()
                assert [r.id for r in rows] == [*stored, resumed]  # none lost, none half-written
                for row in rows:
                    np.testing.assert_array_equal(load_traces(row), sample_codes(row.node_measurement_id))
            print(f"disk full: {len(stored)} stored before, 2 refused, resumed after 1 MiB freed; lost 0")
        finally:
            database.dispose()
