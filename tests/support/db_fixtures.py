"""Fixtures for the storage tests: a real SQLite file, a fresh PostgreSQL schema, sample data.

PostgreSQL tests skip (with the reason) when the server on 127.0.0.1:5432 is unreachable,
except with CI=true, where an unreachable server fails them.
"""
from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import psycopg
import pytest
from sqlalchemy.orm import Session

# Submodule imports: the editable install in .venv maps ``db`` as a namespace package.
from db.database import Database, open_database
from db.measurements import store_measurement
from db.models import MapSource, MeasurementKind, MeasurementRow, NodeRow, NodeState
from db.nodes import upsert_node
from db.records import DetectionInput, DiMapInput, MapGrid, NodeGeometry, NodeInfo, StateChangeInput

PG_PORT = int(os.environ.get("PIPESENTRY_TEST_PG_PORT", "5432"))  # another port: check skip/fail
PG_ADMIN_CONNINFO = f"host=127.0.0.1 port={PG_PORT} user=postgres dbname=test connect_timeout=3"
PG_URL = f"postgresql+psycopg://postgres@127.0.0.1:{PG_PORT}/test"
T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
N_CHANNELS = 8
N_SAMPLES = 2048
GRID = MapGrid(
    axial_start_mm=100.0, axial_step_mm=5.0, axial_count=40, angle_start_deg=0.0, angle_step_deg=10.0, angle_count=36
)


def sqlite_url_for(path: Path) -> str:
    return f"sqlite:///{path}"


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    return sqlite_url_for(tmp_path / "pipesentry.db")


@pytest.fixture
def sqlite_db(sqlite_url: str) -> Iterator[Database]:
    database = open_database(sqlite_url)
    yield database
    database.dispose()


def _postgres_unreachable(reason: str) -> None:
    if os.environ.get("CI") == "true":
        pytest.fail(f"PostgreSQL is required with CI=true: {reason}")
    pytest.skip(f"PostgreSQL unreachable: {reason}")


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """URL of a brand-new schema on the real server (search_path set), dropped afterwards."""
    try:
        admin = psycopg.connect(PG_ADMIN_CONNINFO, autocommit=True)
    except psycopg.OperationalError as error:
        _postgres_unreachable(str(error).strip().splitlines()[0])
    schema = f"pstest_{uuid.uuid4().hex[:16]}"
    with admin:
        admin.execute(f'CREATE SCHEMA "{schema}"')
        try:
            yield f"{PG_URL}?options=-csearch_path%3D{schema}"
        finally:
            admin.execute(f'DROP SCHEMA "{schema}" CASCADE')


@pytest.fixture
def postgres_db(postgres_url: str) -> Iterator[Database]:
    database = open_database(postgres_url)
    yield database
    database.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def any_db(request: pytest.FixtureRequest) -> Database:
    """The same test on a SQLite file and on PostgreSQL."""
    return request.getfixturevalue(f"{request.param}_db")


def node_info(node_id: str = "node-a", n_channels: int = N_CHANNELS) -> NodeInfo:
    return NodeInfo(
        node_id=node_id,
        port_url="serial:///dev/ttyUSB0",
        firmware="1.4.2",
        protocol_version=2,
        n_channels=n_channels,
        fs_hz=2.0e6,
        geometry=NodeGeometry(
            rx_angles_deg=[i * 360.0 / n_channels for i in range(n_channels)],
            tx_angles_deg=[0.0],
            tx_rx_distance_mm=500.0,
            circumference_mm=690.8,
            pipe_length_mm=6000.0,
            tx_axial_mm=1000.0,
        ),
    )


def sample_codes(seed: int, n_channels: int = N_CHANNELS, n_samples: int = N_SAMPLES) -> np.ndarray:
    """Plausible ADC codes: a decaying 85 kHz burst per channel plus noise (int16)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / 2.0e6
    burst = np.sin(2 * np.pi * 85e3 * t) * np.exp(-t / 2e-4)
    signal = 8000 * burst[None, :] * rng.uniform(0.5, 1.0, size=(n_channels, 1))
    noise = rng.normal(0, 30, size=(n_channels, n_samples))
    return np.clip(signal + noise, -32768, 32767).astype(np.int16)


def sample_pixels(seed: int, grid: MapGrid = GRID) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random(grid.shape, dtype=np.float32)


def store_sample(
    session: Session,
    node_id: str = "node-a",
    *,
    acquired_at: datetime = T0,
    kind: MeasurementKind = MeasurementKind.MONITOR,
    seed: int = 0,
    baseline_id: int | None = None,
    detection: DetectionInput | None = None,
    state_change: StateChangeInput | None = None,
    with_map: bool = False,
    velocity_m_s: float | None = None,
    wall_mm: float | None = None,
) -> MeasurementRow:
    """Store one measurement of ``node_id`` (registering the node if needed)."""
    if session.get(NodeRow, node_id) is None:
        upsert_node(session, node_info(node_id), seen_at=acquired_at)
    maps = (
        [DiMapInput(MapSource.GATEWAY, "delay-and-sum", GRID, sample_pixels(seed), baseline_id)] if with_map else []
    )
    return store_measurement(
        session,
        node_id,
        kind=kind,
        acquired_at=acquired_at,
        node_measurement_id=seed,
        codes=sample_codes(seed),
        volts_per_code=1.0 / 32768,
        fs_hz=2.0e6,
        t0_s=1.0e-5,
        averaging=16,
        excitation_hz=85e3,
        cycles=5,
        temperature_c=21.5,
        velocity_m_s=velocity_m_s,
        wall_mm=wall_mm,
        di_maps=maps,
        detection=detection,
        state_change=state_change,
    )


def minutes(n: int) -> timedelta:
    return timedelta(minutes=n)


ALARM = DetectionInput(peak_di=0.42, threshold=0.3, state=NodeState.DAMAGE, axial_mm=1820.0, angle_deg=95.0)
