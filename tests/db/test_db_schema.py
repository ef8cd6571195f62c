"""Specification of opening a database: pragmas, migrations to head, schema checks, locking."""
from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import threading
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect, text
from sqlalchemy.exc import IntegrityError, StatementError

from db.database import Database, open_database
from db.errors import SchemaOutOfDate, StorageBusy
from db.measurements import get_measurement
from db.migrate import alembic_config, head_revision, upgrade_to_head
from db.models import Base
from db.nodes import get_node, upsert_node
from db.sqlite_setup import PAGE_SIZE_BYTES
from tests.support.db_fixtures import T0, node_info, store_sample


def _pragma(database: Database, name: str):
    with database.session() as session:
        return session.execute(text(f"PRAGMA {name}")).scalar_one()


def test_new_sqlite_file_gets_wal_full_sync_fk_incremental_vacuum_and_large_pages(sqlite_db):
    assert _pragma(sqlite_db, "journal_mode") == "wal"
    assert _pragma(sqlite_db, "synchronous") == 2  # FULL
    assert _pragma(sqlite_db, "foreign_keys") == 1
    assert _pragma(sqlite_db, "auto_vacuum") == 2  # INCREMENTAL
    assert _pragma(sqlite_db, "page_size") == PAGE_SIZE_BYTES
    assert _pragma(sqlite_db, "busy_timeout") == 5000


def test_reopening_keeps_the_file_format_and_reapplies_connection_pragmas(sqlite_url):
    open_database(sqlite_url).dispose()
    database = open_database(sqlite_url, busy_timeout_ms=1234)
    try:
        assert _pragma(database, "page_size") == PAGE_SIZE_BYTES
        assert _pragma(database, "auto_vacuum") == 2
        assert _pragma(database, "busy_timeout") == 1234
        assert _pragma(database, "foreign_keys") == 1
    finally:
        database.dispose()


def test_new_database_is_migrated_to_head(any_db):
    assert any_db.schema_revision() == head_revision()


def test_migrations_produce_exactly_the_schema_the_models_describe(any_db):
    with any_db.engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        differences = compare_metadata(context, Base.metadata)
    assert differences == []


def test_read_only_open_of_an_empty_database_says_schema_out_of_date(sqlite_url):
    with pytest.raises(SchemaOutOfDate, match=rf"empty .* needs {head_revision()}"):
        open_database(sqlite_url, upgrade=False)


def test_read_only_open_of_a_migrated_database_succeeds(sqlite_url):
    open_database(sqlite_url).dispose()
    database = open_database(sqlite_url, upgrade=False)
    assert database.schema_revision() == head_revision()
    database.dispose()


def test_a_database_from_a_newer_release_is_refused(sqlite_url):
    open_database(sqlite_url).dispose()
    database = open_database(sqlite_url)
    with database.write() as session:
        session.execute(text("UPDATE alembic_version SET version_num = '9999'"))
    database.dispose()
    with pytest.raises(SchemaOutOfDate, match="9999") as raised:
        open_database(sqlite_url, upgrade=False)
    assert raised.value.current == "9999"
    with pytest.raises(SchemaOutOfDate, match="at least as new"):
        open_database(sqlite_url, upgrade=True)  # the gateway must not touch it either


def test_postgres_read_only_open_checks_the_schema_too(postgres_url):
    with pytest.raises(SchemaOutOfDate):
        open_database(postgres_url, upgrade=False)
    open_database(postgres_url).dispose()
    open_database(postgres_url, upgrade=False).dispose()


def test_timestamps_come_back_timezone_aware_utc(any_db):
    seen = datetime(2026, 3, 1, 13, 30, tzinfo=timezone(timedelta(hours=1)))
    with any_db.write() as session:
        upsert_node(session, node_info("node-tz"), seen_at=seen)
    with any_db.session() as session:
        node = get_node(session, "node-tz")
        assert node.last_seen_at == seen
        assert node.last_seen_at.tzinfo is not None
        assert node.last_seen_at.utcoffset() == timedelta(0)


def test_naive_datetimes_are_rejected(any_db):
    with pytest.raises(StatementError, match="naive datetime") as raised:
        with any_db.write() as session:
            upsert_node(session, node_info("node-naive"), seen_at=datetime(2026, 3, 1, 12, 0))
    assert isinstance(raised.value.orig, ValueError)


def test_write_takes_the_sqlite_write_lock_at_begin(sqlite_url):
    """Even a write() that starts with a SELECT holds the lock, so a second writer waits at
    BEGIN (and gives up as StorageBusy) instead of failing half-way on a lock upgrade."""
    holder = open_database(sqlite_url)
    contender = open_database(sqlite_url, busy_timeout_ms=100)
    locked = threading.Event()
    release = threading.Event()

    def hold_write_lock() -> None:
        with holder.write() as session:
            session.execute(text("SELECT 1"))  # the session's first statement: BEGIN IMMEDIATE
            locked.set()
            release.wait(timeout=10)

    thread = threading.Thread(target=hold_write_lock)
    thread.start()
    try:
        assert locked.wait(timeout=10)
        with pytest.raises(StorageBusy):
            with contender.write() as session:
                session.execute(text("SELECT count(*) FROM nodes"))
        with contender.session() as session:  # WAL: readers are not blocked by the writer
            assert session.execute(text("SELECT count(*) FROM nodes")).scalar_one() == 0
    finally:
        release.set()
        thread.join(timeout=10)
        holder.dispose()
        contender.dispose()


def test_write_commits_on_success_and_rolls_back_on_error(any_db):
    with any_db.write() as session:
        upsert_node(session, node_info("kept"), seen_at=T0)
    with pytest.raises(RuntimeError):
        with any_db.write() as session:
            upsert_node(session, node_info("discarded"), seen_at=T0)
            session.flush()
            raise RuntimeError("boom")
    with any_db.session() as session:
        assert [n for (n,) in session.execute(text("SELECT node_id FROM nodes ORDER BY node_id"))] == ["kept"]


def test_in_memory_sqlite_is_refused():
    with pytest.raises(ValueError, match="file URL"):
        open_database("sqlite://")


@pytest.mark.e2e
def test_an_installed_copy_of_the_package_migrates_without_the_repository(tmp_path):
    """What a wheel ships (the .py files and script.py.mako) is all migrating needs."""
    repo_db = Path(__file__).resolve().parents[2] / "db"
    site = tmp_path / "site-packages"
    for source in [*repo_db.rglob("*.py"), *repo_db.rglob("*.mako")]:
        target = site / "db" / source.relative_to(repo_db)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
    workdir = tmp_path / "elsewhere"
    workdir.mkdir()
    url = f"sqlite:///{tmp_path / 'installed.db'}"
    program = (
        "import db.migrate, sys; from db.database import open_database; "
        "d = open_database(sys.argv[1]); print(db.migrate.__file__); print(d.schema_revision())"
    )
    result = subprocess.run(
        [sys.executable, "-c", program, url],
        cwd=workdir,
        env={**os.environ, "PYTHONPATH": str(site)},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    module_file, revision = result.stdout.split()
    assert module_file.startswith(str(site))
    assert revision == head_revision()


def test_a_database_of_the_first_release_upgrades_keeping_its_nodes(sqlite_url):
    from sqlalchemy import create_engine

    engine = create_engine(sqlite_url)
    with engine.connect() as connection:  # the schema as release 0001 left it, with a node in it
        command.upgrade(alembic_config(connection), "0001")
        connection.execute(text(
            "INSERT INTO nodes (node_id, port_url, firmware, protocol_version, n_channels, fs_hz, geometry,"
            " first_seen_at, last_seen_at, online, error_counters, state)"
            " VALUES ('old-node', 'serial:///dev/ttyUSB0', '1.0.0', 2, 8, 2000000.0, '{}',"
            " '2026-11-01 00:00:00.000000', '2026-11-02 00:00:00.000000', 1, '{}', 'damage')"
        ))
        connection.commit()
    engine.dispose()
    database = open_database(sqlite_url)  # the gateway's open: upgrades to head
    try:
        assert database.schema_revision() == head_revision() != "0001"
        with database.session() as session:
            node = get_node(session, "old-node")
            assert node.state.value == "damage" and node.decommissioned_at is None and node.label is None
    finally:
        database.dispose()


def database_of_release(url: str, revision: str) -> int:
    """The database at ``url`` migrated to ``revision`` only, holding a node and one record stored as
    release 0003 stored them (the schema the later revisions kept compatible); returns the record's id."""
    from sqlalchemy import create_engine
    from sqlalchemy.orm import Session

    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            command.upgrade(alembic_config(connection), revision)
            connection.commit()
            with Session(connection) as session:
                store_node_as_of_0003(session)
                old_id = store_sample_as_of_0003(session)
                session.commit()
    finally:
        engine.dispose()
    return old_id


@pytest.mark.parametrize("url_fixture", ["sqlite_url", pytest.param("postgres_url", marks=pytest.mark.postgres)])
def test_a_database_of_release_0003_upgrades_keeping_its_records_which_export_with_the_default_velocity(
    request, url_fixture
):

    from db.measurement_build import stored_measurement
    from db.measurements import load_traces
    from imaging.measurement import DEFAULT_VELOCITY_M_S

    url = request.getfixturevalue(url_fixture)
    old_id = database_of_release(url, "0003")  # a record as release 0003 stored it (no velocity, no wall)
    database = open_database(url)  # the gateway's open: upgrades to head
    try:
        assert database.schema_revision() == head_revision() != "0003"
        with database.session() as session:
            row = get_measurement(session, old_id)
            assert (row.velocity_m_s, row.wall_mm) == (None, None) and load_traces(row).shape == (8, 2048)
            old = stored_measurement(session, old_id)
            assert old.velocity_m_s == DEFAULT_VELOCITY_M_S and old.wall_mm is None
        with database.write() as session:
            new_id = store_sample(session, seed=2, velocity_m_s=3205.0, wall_mm=6.0).id
        with database.session() as session:
            new = stored_measurement(session, new_id)
            assert (new.velocity_m_s, new.wall_mm) == (3205.0, 6.0)
    finally:
        database.dispose()


def store_node_as_of_0003(session) -> None:
    """Insert node-a with only the columns revision 0003 has (the ORM model is head's)."""
    from sqlalchemy import insert

    from db.models import NodeRow, NodeState

    info = node_info()
    session.execute(insert(NodeRow).values(
        node_id=info.node_id, port_url=info.port_url, firmware=info.firmware, protocol_version=info.protocol_version,
        n_channels=info.n_channels, fs_hz=info.fs_hz, geometry=info.geometry.model_dump(mode="json"),
        first_seen_at=T0, last_seen_at=T0, online=True, error_counters={}, state=NodeState.COMMISSIONING,
    ))


def store_sample_as_of_0003(session) -> int:
    """Insert a measurement with only the columns revision 0003 has (the ORM model is head's)."""
    from sqlalchemy import insert

    from db import blobs
    from db.models import MeasurementKind, MeasurementRow
    from tests.support.db_fixtures import sample_codes

    encoded = blobs.encode_array(sample_codes(1), blobs.TRACE_DTYPE)
    result = session.execute(insert(MeasurementRow).values(
        node_id="node-a", kind=MeasurementKind.BASELINE, acquired_at=T0, node_measurement_id=1, temperature_c=21.5,
        averaging=16, fs_hz=2.0e6, t0_s=1e-5, n_channels=8, n_samples=2048, volts_per_code=1.0 / 32768,
        excitation_hz=85e3, cycles=5, traces_blob=encoded.data, traces_codec=encoded.codec, traces_dtype=encoded.dtype,
        traces_sha256=encoded.sha256, traces_nbytes=len(encoded.data), traces_pruned_at=None, stored_at=T0,
    ))
    return int(result.inserted_primary_key[0])


@pytest.mark.parametrize("url_fixture", ["sqlite_url", pytest.param("postgres_url", marks=pytest.mark.postgres)])
def test_a_database_of_release_0009_upgrades_keeping_its_nodes_and_records_and_can_hold_a_node_never_seen(
    request, url_fixture
):
    from sqlalchemy import insert

    from db.models import NodeRow
    from db.nodes import register_configured_node

    url = request.getfixturevalue(url_fixture)
    # A node with a measurement referring to it (the table is rebuilt on SQLite only if its foreign keys let it).
    old_id = database_of_release(url, "0009")
    database = open_database(url)
    try:
        assert database.schema_revision() == head_revision() != "0009"
        with database.session() as session:
            old = get_node(session, "node-a")
            assert (old.watched_since, old.first_seen_at, old.last_seen_at, old.n_channels) == (T0, T0, T0, 8)
            assert not old.never_seen and get_measurement(session, old_id).node_id == "node-a"
        later = T0 + timedelta(days=1)
        with database.write() as session:
            assert register_configured_node(session, "node-b", port_url="serial:///dev/ttyUSB1", now=later)
        with database.session() as session:
            new = get_node(session, "node-b")
            assert new.never_seen and new.watched_since == later and new.first_seen_at is None
            assert (new.firmware, new.protocol_version, new.n_channels, new.fs_hz, new.geometry) == (None,) * 5
        with pytest.raises(IntegrityError, match="watched_since"), database.write() as session:  # when it was registered is never unknown
            session.execute(insert(NodeRow).values(node_id="node-c", port_url="tcp://x:1", online=False,
                                                   error_counters={}, state="commissioning"))
    finally:
        database.dispose()


@pytest.mark.parametrize("url_fixture", ["sqlite_url", pytest.param("postgres_url", marks=pytest.mark.postgres)])
def test_downgrading_to_0009_forgets_the_nodes_never_seen_with_their_events_and_keeps_the_others(request, url_fixture):
    from alerts.config import AlertingSettings
    from alerts.outages import check_outages
    from db.nodes import register_configured_node

    database = open_database(request.getfixturevalue(url_fixture))
    try:
        with database.write() as session:
            upsert_node(session, node_info("node-a"), seen_at=T0)
            store_sample(session, "node-a")
            register_configured_node(session, "node-b", port_url="tcp://127.0.0.1:1", now=T0)
            later = T0 + timedelta(hours=2)
            added = check_outages(session, AlertingSettings(), now=later, watching_since=T0)
            assert {event.payload["node_id"] for event in added} == {"node-a", "node-b"}
        with database.engine.connect() as connection:
            command.downgrade(alembic_config(connection), "0009")
            connection.commit()
            nodes = connection.execute(text("SELECT node_id FROM nodes")).scalars().all()
            events = connection.execute(text("SELECT node_id FROM events")).scalars().all()
            columns = {c["name"]: c["nullable"] for c in inspect(connection).get_columns("nodes")}
        assert nodes == ["node-a"] and events == ["node-a"]
        assert "watched_since" not in columns and not columns["n_channels"] and not columns["last_seen_at"]
        upgrade_to_head(database.engine)
        assert database.schema_revision() == head_revision()
    finally:
        database.dispose()


@pytest.mark.parametrize("url_fixture", ["sqlite_url", pytest.param("postgres_url", marks=pytest.mark.postgres)])
def test_trace_requests_of_an_older_release_are_kept_can_be_refused_and_going_down_a_refused_one_is_forgotten(
    request, url_fixture
):
    from sqlalchemy import insert, select

    from db.models import TraceRequestRow, TraceRequestStatus

    url = request.getfixturevalue(url_fixture)
    old_id = database_of_release(url, "0009")  # trace_requests as revisions 0009 to 0011 have it
    with _engine(url) as engine, engine.begin() as connection:
        connection.execute(text(  # a request the gateway answered held, as those revisions stored it
            "INSERT INTO trace_requests (measurement_id, measurement_uid, gateway_id, site, status, requested_by, "
            "requested_at, answered_at) VALUES (:m, 'gw-n1/measurement/1', 'gw-n1', 'north', 'held', 'op', :t, :t)"
        ), {"m": old_id, "t": T0})
    database = open_database(url)
    try:
        assert database.schema_revision() == head_revision() != "0009"
        with database.write() as session:
            held = session.scalars(select(TraceRequestRow)).one()
            assert (held.status, held.answered_at, held.refused_at, held.refusal) == ("held", T0, None, None)
            held.status, held.refused_at, held.refusal = TraceRequestStatus.REFUSED, T0, "HTTP 422 ingest-bad-record: x"
            other = store_sample(session, seed=2)
            session.execute(insert(TraceRequestRow).values(
                measurement_id=other.id, measurement_uid="gw-n1/measurement/2", gateway_id="gw-n1", site="north",
                status=TraceRequestStatus.HELD, requested_by="op", requested_at=T0))
        with pytest.raises(IntegrityError), database.write() as session:  # the CHECK still holds the list
            session.execute(text("UPDATE trace_requests SET status = 'lost'"))
        with database.engine.connect() as connection:
            command.downgrade(alembic_config(connection), "0011")
            connection.commit()
            rows = connection.execute(text("SELECT measurement_uid, status FROM trace_requests")).all()
            columns = {c["name"] for c in inspect(connection).get_columns("trace_requests")}
        assert [tuple(row) for row in rows] == [("gw-n1/measurement/2", "held")]  # the refused one forgotten
        assert not {"refused_at", "refusal"} & columns
        with pytest.raises(IntegrityError), database.engine.begin() as connection:  # 0011 holds no refused
            connection.execute(text("UPDATE trace_requests SET status = 'refused'"))
        upgrade_to_head(database.engine)
        assert database.schema_revision() == head_revision()
    finally:
        database.dispose()


@contextmanager
def _engine(url: str):
    from sqlalchemy import create_engine

    engine = create_engine(url)
    try:
        yield engine
    finally:
        engine.dispose()


def test_migrations_downgrade_to_empty_and_upgrade_again(any_db):
    with any_db.engine.connect() as connection:
        command.downgrade(alembic_config(connection), "base")
        connection.commit()
    assert any_db.schema_revision() is None
    with any_db.session() as session:
        tables = set(inspect(session.connection()).get_table_names()) - {"alembic_version"}
    assert tables == set()
    upgrade_to_head(any_db.engine)
    assert any_db.schema_revision() == head_revision()


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "db", *args], capture_output=True, text=True, timeout=60, cwd=Path(__file__).parents[2]
    )


@pytest.mark.e2e
def test_command_line_upgrades_and_reports_the_revision(sqlite_url):
    # `current` reads: a missing file is said, not created (it used to be, and reported "empty").
    missing = _cli("current", "--url", sqlite_url)
    assert missing.returncode == 2 and "no database file" in missing.stderr
    assert not Path(sqlite_url.removeprefix("sqlite:///")).exists()
    sqlite3.connect(sqlite_url.removeprefix("sqlite:///")).close()  # an empty database file
    assert _cli("current", "--url", sqlite_url).stdout.strip() == "empty"
    assert _cli("upgrade", "--url", sqlite_url).returncode == 0
    assert _cli("current", "--url", sqlite_url).stdout.strip() == head_revision()


@pytest.mark.e2e
def test_command_line_reports_a_storage_error_in_one_line_with_exit_code_2(sqlite_url):
    open_database(sqlite_url).dispose()
    database = open_database(sqlite_url)
    with database.write() as session:
        session.execute(text("UPDATE alembic_version SET version_num = 'future'"))
    database.dispose()
    result = _cli("upgrade", "--url", sqlite_url)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "future" in result.stderr and "Traceback" not in result.stderr
