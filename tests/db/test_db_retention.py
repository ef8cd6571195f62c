"""Specification of retention: old raw traces go, in bounded batches; everything else stays."""
from __future__ import annotations

from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import func, select, text

from db.baselines import set_active_baseline
from db.errors import BaselineError, TracesPruned
from db.measurements import get_measurement, load_pixels, load_traces
from db.models import DetectionRow, MeasurementKind, MeasurementRow
from db.queries import di_maps_for
from db.retention import prune_traces
from tests.support.db_fixtures import ALARM, T0, minutes, sample_codes, sample_pixels, store_sample

NOW = T0 + timedelta(days=100)
KEEP = timedelta(days=30)


def _old(i: int):
    return T0 + minutes(i)  # 100 days before NOW: due for pruning


def test_old_traces_are_pruned_and_results_stay(any_db):
    with any_db.write() as session:
        old = [store_sample(session, acquired_at=_old(i), seed=i, with_map=True, detection=None).id for i in range(7)]
        recent = store_sample(session, acquired_at=NOW - timedelta(days=1), seed=50).id
    pruned = prune_traces(any_db.write, KEEP, batch_size=3, now=NOW)
    assert pruned == 7
    with any_db.session() as session:
        for measurement_id in old:
            row = get_measurement(session, measurement_id)
            assert row.traces_pruned_at == NOW
            with pytest.raises(TracesPruned):
                load_traces(row)
            (di_map,) = di_maps_for(session, measurement_id)
            np.testing.assert_array_equal(load_pixels(di_map), sample_pixels(old.index(measurement_id)))
        np.testing.assert_array_equal(load_traces(get_measurement(session, recent)), sample_codes(50))
        assert session.scalar(select(func.count()).select_from(MeasurementRow)) == 8


def test_detections_survive_pruning(any_db):
    with any_db.write() as session:
        measurement_id = store_sample(session, acquired_at=_old(0), detection=ALARM).id
    assert prune_traces(any_db.write, KEEP, batch_size=10, now=NOW) == 1
    with any_db.session() as session:
        detection = session.scalars(select(DetectionRow)).one()
        assert (detection.measurement_id, detection.peak_di) == (measurement_id, ALARM.peak_di)


def test_baselines_current_or_past_are_never_pruned(any_db):
    with any_db.write() as session:
        recorded = store_sample(session, kind=MeasurementKind.BASELINE, acquired_at=_old(0), seed=1).id
        promoted = store_sample(session, kind=MeasurementKind.MONITOR, acquired_at=_old(1), seed=2).id
        replaced = store_sample(session, kind=MeasurementKind.MONITOR, acquired_at=_old(2), seed=3).id
        plain = store_sample(session, kind=MeasurementKind.MONITOR, acquired_at=_old(3), seed=4).id
        set_active_baseline(session, "node-a", replaced, created_by="x", reason="first")
        set_active_baseline(session, "node-a", promoted, created_by="x", reason="after repair")
    assert prune_traces(any_db.write, KEEP, batch_size=10, now=NOW) == 1
    with any_db.session() as session:
        for measurement_id, seed in ((recorded, 1), (promoted, 2), (replaced, 3)):
            np.testing.assert_array_equal(load_traces(get_measurement(session, measurement_id)), sample_codes(seed))
        assert get_measurement(session, plain).traces_pruned_at == NOW


def test_pruned_measurement_cannot_become_a_baseline(any_db):
    with any_db.write() as session:
        measurement_id = store_sample(session, acquired_at=_old(0)).id
    prune_traces(any_db.write, KEEP, batch_size=10, now=NOW)
    with pytest.raises(BaselineError, match="pruned"):
        with any_db.write() as session:
            set_active_baseline(session, "node-a", measurement_id, created_by="x", reason="r")


def test_each_batch_is_its_own_bounded_transaction(sqlite_db):
    with sqlite_db.write() as session:
        for i in range(10):
            store_sample(session, acquired_at=_old(i), seed=i)
    transactions: list[int] = []

    def counting_write():
        transactions.append(1)
        return sqlite_db.write()

    assert prune_traces(counting_write, KEEP, batch_size=4, now=NOW, max_batches=2) == 8  # stops at the bound
    assert len(transactions) == 2
    assert prune_traces(sqlite_db.write, KEEP, batch_size=4, now=NOW) == 2
    assert prune_traces(sqlite_db.write, KEEP, batch_size=4, now=NOW) == 0


def test_sqlite_file_gives_the_pruned_space_back(sqlite_db):
    with sqlite_db.write() as session:
        for i in range(40):
            store_sample(session, acquired_at=_old(i), seed=i)
    with sqlite_db.session() as session:
        pages_before = session.execute(text("PRAGMA page_count")).scalar_one()
    prune_traces(sqlite_db.write, KEEP, batch_size=16, now=NOW)
    with sqlite_db.session() as session:
        assert session.execute(text("PRAGMA freelist_count")).scalar_one() == 0
        pages_after = session.execute(text("PRAGMA page_count")).scalar_one()
        assert session.execute(text("PRAGMA integrity_check")).scalar_one() == "ok"
    # Each ~20 kB blob had at least one 16 KiB overflow page of its own; all must be gone.
    assert pages_before - pages_after >= 40


def test_invalid_arguments_are_refused(sqlite_db):
    with pytest.raises(ValueError, match="batch_size must be >= 1"):
        prune_traces(sqlite_db.write, KEEP, batch_size=0)
    with pytest.raises(ValueError, match="older_than must not be negative"):
        prune_traces(sqlite_db.write, -KEEP, batch_size=10)
