"""Specification of baselines: exactly one active per node, history kept, sane choices only."""
from __future__ import annotations

import pytest
from sqlalchemy import insert
from sqlalchemy.exc import IntegrityError

from db.baselines import (
    active_baseline,
    active_baseline_measurement,
    baseline_history,
    library_baseline_ids,
    set_active_baseline,
)
from db.errors import BaselineError, NotFound
from db.models import BaselineRow, MeasurementKind
from tests.support.db_fixtures import T0, minutes, store_sample


def test_a_node_without_baseline_has_none(any_db):
    with any_db.write() as session:
        store_sample(session)
        assert active_baseline(session, "node-a") is None
        assert active_baseline_measurement(session, "node-a") is None


def test_setting_a_new_baseline_deactivates_the_old_one_and_keeps_history(any_db):
    with any_db.write() as session:
        first = store_sample(session, kind=MeasurementKind.BASELINE, seed=1).id
        second = store_sample(session, kind=MeasurementKind.BASELINE, seed=2, acquired_at=T0 + minutes(1)).id
        set_active_baseline(session, "node-a", first, created_by="commissioning", reason="install", now=T0)
    with any_db.write() as session:
        set_active_baseline(
            session, "node-a", second, created_by="alice", reason="after repair", now=T0 + minutes(60)
        )
    with any_db.session() as session:
        assert active_baseline(session, "node-a").measurement_id == second
        assert active_baseline_measurement(session, "node-a").id == second
        history = baseline_history(session, "node-a")
        assert [(b.measurement_id, b.active, b.created_by) for b in history] == [
            (second, True, "alice"),
            (first, False, "commissioning"),
        ]
        assert history[1].deactivated_at == T0 + minutes(60)


def test_baselines_of_different_nodes_are_independent(any_db):
    with any_db.write() as session:
        a = store_sample(session, "node-a", kind=MeasurementKind.BASELINE).id
        b = store_sample(session, "node-b", kind=MeasurementKind.BASELINE).id
        set_active_baseline(session, "node-a", a, created_by="x", reason="r")
        set_active_baseline(session, "node-b", b, created_by="x", reason="r")
    with any_db.session() as session:
        assert active_baseline(session, "node-a").measurement_id == a
        assert active_baseline(session, "node-b").measurement_id == b


def test_the_database_itself_refuses_a_second_active_baseline(any_db):
    """The partial unique index backs up set_active_baseline against any other writer."""
    with any_db.write() as session:
        measurement_id = store_sample(session, kind=MeasurementKind.BASELINE).id
        set_active_baseline(session, "node-a", measurement_id, created_by="x", reason="r")
    row = dict(node_id="node-a", measurement_id=measurement_id, created_by="rogue", created_at=T0, reason="r")
    with pytest.raises(IntegrityError):
        with any_db.write() as session:
            session.execute(insert(BaselineRow).values(**row, active=True))
    with any_db.write() as session:  # inactive history rows are unlimited
        session.execute(insert(BaselineRow).values(**row, active=False))
        session.execute(insert(BaselineRow).values(**row, active=False))


def test_a_measurement_of_another_node_cannot_be_the_baseline(any_db):
    with any_db.write() as session:
        store_sample(session, "node-a")
        foreign = store_sample(session, "node-b", kind=MeasurementKind.BASELINE).id
    with pytest.raises(BaselineError, match="node-b"):
        with any_db.write() as session:
            set_active_baseline(session, "node-a", foreign, created_by="x", reason="r")


def test_unknown_measurement_or_node_is_not_found(any_db):
    with any_db.write() as session:
        store_sample(session)
    with pytest.raises(NotFound):
        with any_db.write() as session:
            set_active_baseline(session, "node-a", 123456, created_by="x", reason="r")
    with pytest.raises(NotFound):
        with any_db.write() as session:
            set_active_baseline(session, "nobody", 1, created_by="x", reason="r")


def test_a_monitor_measurement_may_be_promoted_to_baseline(any_db):
    with any_db.write() as session:
        monitor = store_sample(session, kind=MeasurementKind.MONITOR).id
        set_active_baseline(session, "node-a", monitor, created_by="bob", reason="new normal after repair")
    with any_db.session() as session:
        assert active_baseline(session, "node-a").measurement_id == monitor


def test_an_inactive_baseline_joins_the_library_the_gateway_compares_with(sqlite_db):
    from service import baselines, schemas

    with sqlite_db.write() as session:
        commissioning = store_sample(session, "node-a", kind=MeasurementKind.BASELINE, seed=1)
        set_active_baseline(session, "node-a", commissioning.id, created_by="gateway", reason="commissioning")
        summer = store_sample(session, "node-a", seed=2)  # a monitor measurement on a hot day
    with sqlite_db.session() as session:
        assert library_baseline_ids(session, "node-a", 24) == [commissioning.id]
    with sqlite_db.write() as session:
        baselines.create(session, "node-a", schemas.BaselineCreate(measurement_id=summer.id, reason="35 degC, sound",
                                                                   activate=False), who="operator:kim")
    with sqlite_db.session() as session:
        assert library_baseline_ids(session, "node-a", 24) == [commissioning.id, summer.id]
        assert active_baseline(session, "node-a").measurement_id == commissioning.id
