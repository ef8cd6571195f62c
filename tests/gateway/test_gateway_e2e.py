"""The gateway daemon as a real process against mock nodes on pseudo-terminals, with a real SQLite file."""
from __future__ import annotations

import random
import socket
import sqlite3
import time
from pathlib import Path

import pytest
from sqlalchemy import func, select

from db.database import open_database
from db.measurements import load_traces
from db.models import (
    BaselineRow,
    DetectionRow,
    DiMapRow,
    EventRow,
    MeasurementKind,
    MeasurementRow,
    NodeRow,
    StateChangeRow,
)
from imaging.detection import default_threshold
from tests.support.process_harness import (
    gateway_config,
    gateway_node,
    scenario_node,
    start_gateway,
    start_mock_nodes,
    wait_for_links,
    wait_until,
)

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(240)]  # runs the system's real processes

def write_scenario(path: Path, quiet: list[str], damaged: dict[str, float] | None = None) -> Path:
    """Quiet nodes, and nodes whose paper notch (200 mm, 90 deg) appears at the given scenario time."""
    text = "".join(scenario_node(n, 100 + i) for i, n in enumerate(quiet))
    text += "".join(scenario_node(n, 200 + i, defect=(200.0, 90.0, t)) for i, (n, t) in enumerate((damaged or {}).items()))
    path.write_text(text)
    return path


@pytest.fixture
def run_dir(tmp_path):
    return tmp_path


def counts(db_url: str) -> dict[str, int]:
    db = open_database(db_url, upgrade=False)
    try:
        with db.session() as s:
            rows = s.execute(select(MeasurementRow.node_id, func.count()).group_by(MeasurementRow.node_id)).all()
            return dict(rows)
    finally:
        db.dispose()


def node_state(db_url: str, node_id: str) -> str:
    """The node's stored state, read through a fresh connection."""
    db = open_database(db_url, upgrade=False)
    try:
        with db.session() as s:
            return s.get(NodeRow, node_id).state.value
    finally:
        db.dispose()


def latest_detection(session, node_id: str) -> DetectionRow:
    return session.scalars(
        select(DetectionRow).where(DetectionRow.node_id == node_id).order_by(DetectionRow.id.desc())).first()


def assert_near_the_notch(detection: DetectionRow) -> None:
    """The detection's position lies within 20 mm of the scenario's notch (200 mm, 90 deg)."""
    assert detection.axial_mm is not None
    arc = min(abs(detection.angle_deg - 90.0), 360 - abs(detection.angle_deg - 90.0)) * 360.03 / 360
    assert ((detection.axial_mm - 200.0) ** 2 + arc**2) ** 0.5 < 20.0, (detection.axial_mm, detection.angle_deg)


def start_fleet(run_dir: Path, scenario: Path, node_ids: list[str], *mock_args: str, **node_kw):
    links = run_dir / "links"
    mock = start_mock_nodes(scenario, links, run_dir, *mock_args)
    wait_for_links(links, node_ids, mock)
    db_path = run_dir / "gateway.db"
    config = run_dir / "gateway.toml"
    config.write_text(gateway_config(db_path, [gateway_node(n, links, **node_kw) for n in node_ids]))
    return mock, config, f"sqlite:///{db_path}"


def test_several_nodes_many_cycles_every_measurement_stored_and_readable(run_dir):
    ids = ["node-a", "node-b", "node-c"]
    mock, config, url = start_fleet(run_dir, write_scenario(run_dir / "s.toml", ids), ids)
    gw = start_gateway(config, run_dir)
    try:
        wait_until(lambda: (c := counts(url)) and all(c.get(n, 0) >= 6 for n in ids), 120, 0.5,
                   what="6 measurements per node")
        t0 = time.monotonic()
        assert gw.terminate(timeout_s=10) == 0, gw.stderr[-3000:]
        assert time.monotonic() - t0 < 5.0, "SIGTERM must stop the gateway within 5 s"
        # Routine state changes are INFO; WARNING is kept for what needs a look (issue 16, item 9).
        assert "INFO node=node-a pipesentry.gateway: state commissioning -> calibrating" in gw.stderr
        assert "WARNING node=node-a pipesentry.gateway: state commissioning" not in gw.stderr
    finally:
        gw.close()
        mock.close()
    db = open_database(url, upgrade=False)
    with db.session() as s:
        for node_id in ids:
            node = s.get(NodeRow, node_id)
            assert node is not None and node.n_channels == 16
            rows = s.scalars(select(MeasurementRow).where(MeasurementRow.node_id == node_id)).all()
            assert rows[0].kind == MeasurementKind.BASELINE
            for row in rows:
                codes = load_traces(row)  # verifies the checksum
                assert codes.shape == (16, 6000)
            monitors = [r for r in rows if r.kind == MeasurementKind.MONITOR]
            for row in monitors:
                sources = {m.source.value for m in s.scalars(select(DiMapRow).where(DiMapRow.measurement_id == row.id))}
                assert sources == {"gateway", "node"}
                assert s.scalar(select(DetectionRow).where(DetectionRow.measurement_id == row.id)) is not None
            active = s.scalars(select(BaselineRow).where(BaselineRow.node_id == node_id, BaselineRow.active)).all()
            assert len(active) == 1 and active[0].measurement_id == rows[0].id
    db.dispose()
    log = (run_dir / "gateway.err").read_text()
    assert "node=node-a" in log and "node=node-b" in log


def test_appearing_defect_is_flagged_near_its_true_position_and_quiet_node_is_not(run_dir):
    ids = ["quiet", "damaged"]
    # The notch appears well after commissioning and calibration (4 cycles), which assume a sound pipe.
    scenario = write_scenario(run_dir / "s.toml", ["quiet"], {"damaged": 30.0})
    mock, config, url = start_fleet(run_dir, scenario, ids)
    gw = start_gateway(config, run_dir)
    db = None
    try:
        wait_until(lambda: node_state(url, "damaged") == "damage", 150, 0.5, what="the damaged node flagged")
        db = open_database(url, upgrade=False)
        with db.session() as s:
            assert_near_the_notch(latest_detection(s, "damaged"))
            changes = [c.to_state.value for c in s.scalars(
                select(StateChangeRow).where(StateChangeRow.node_id == "damaged").order_by(StateChangeRow.id))]
            assert "damage" in changes
            quiet_states = set(s.scalars(select(DetectionRow.state).where(DetectionRow.node_id == "quiet")).all())
            assert {st.value for st in quiet_states} <= {"ok", "calibrating"}
            assert s.get(NodeRow, "quiet").state.value in ("ok", "calibrating")
    finally:
        if db is not None:
            db.dispose()
        gw.close()
        mock.close()


def test_unplugged_and_replugged_node_recovers_without_partial_records(run_dir):
    ids = ["flaky"]
    mock, config, url = start_fleet(
        run_dir, write_scenario(run_dir / "s.toml", ids), ids, "--disconnect-every-s", "2.5", "--reconnect-after-s", "1"
    )
    gw = start_gateway(config, run_dir)
    try:
        # Eight measurements can fit between two pulls: wait for a pull first, then for more after it.
        wait_until(lambda: "reopening with backoff" in gw.stderr, 60, 0.2, what="the cable pulled and noticed")
        after_pull = counts(url).get("flaky", 0)
        wait_until(lambda: counts(url).get("flaky", 0) >= max(8, after_pull + 3), 150, 0.5,
                   what="measurements again after the replug")
    finally:
        gw.close()
        mock.close()
    db = open_database(url, upgrade=False)
    with db.session() as s:
        for row in s.scalars(select(MeasurementRow)).all():
            assert load_traces(row).shape == (16, 6000)
    db.dispose()


def test_kill_9_during_writes_never_corrupts_or_half_writes(run_dir):
    ids = ["k1", "k2"]
    mock, config, url = start_fleet(run_dir, write_scenario(run_dir / "s.toml", ids), ids, interval_s=0.05)
    rng = random.Random(7)
    try:
        for round_no in range(5):
            gw = start_gateway(config, run_dir, name=f"gateway{round_no}")
            before = sum(counts(url).values()) if (run_dir / "gateway.db").exists() else 0
            wait_until(lambda before=before: sum(counts(url).values()) > before, 60, 0.1, what="a new measurement")
            time.sleep(rng.uniform(0.0, 0.8))  # land the kill at a random point of a cycle
            gw.kill()
            gw.close()
    finally:
        mock.close()
    con = sqlite3.connect(run_dir / "gateway.db")
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()
    db = open_database(url, upgrade=False)
    with db.session() as s:
        rows = s.scalars(select(MeasurementRow)).all()
        assert len(rows) >= 5
        for row in rows:
            assert load_traces(row).shape == (16, 6000)
            if row.kind == MeasurementKind.MONITOR:
                assert s.scalar(select(DetectionRow).where(DetectionRow.measurement_id == row.id)) is not None
                assert s.scalar(select(func.count()).select_from(DiMapRow).where(DiMapRow.measurement_id == row.id)) >= 1
    db.dispose()


def test_systemd_gets_ready_and_watchdog_pings(run_dir):
    ids = ["sd"]
    mock, config, _url = start_fleet(run_dir, write_scenario(run_dir / "s.toml", ids), ids)
    sock_path = run_dir / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.settimeout(20)
    gw = start_gateway(config, run_dir, env={"NOTIFY_SOCKET": str(sock_path), "WATCHDOG_USEC": "200000"})
    try:
        messages = []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and sum("WATCHDOG=1" in m for m in messages) < 3:
            messages.append(sock.recv(4096).decode())
        assert messages[0].startswith("READY=1")
        assert sum("WATCHDOG=1" in m for m in messages) >= 3
        assert gw.terminate() == 0
        sock.settimeout(2)
        for _ in range(500):  # the datagrams sent before exit are still queued on our socket
            messages.append(sock.recv(4096).decode())
            if "STOPPING=1" in messages[-1]:
                break
        assert "STOPPING=1" in messages[-1]
    finally:
        sock.close()
        gw.close()
        mock.close()


def test_no_flag_on_sound_pipes_under_noise_and_temperature_drift(run_dir):
    """+-2 degC over a 40 s 'day': compensation keeps sound pipes below the documented default threshold.

    The threshold is fixed (absolute, the method's default) rather than calibrated, so that a
    calibration which happened to see the drift cannot hide a compensation failure.
    """
    ids = ["drift-a", "drift-b"]
    scenario = run_dir / "s.toml"
    drift = {"mean_c": 20.0, "daily_amplitude_c": 2.0, "period_s": 40.0, "jitter_c": 0.05}
    scenario.write_text("".join(scenario_node(n, 300 + i, temperature=drift) for i, n in enumerate(ids)))
    fixed = {"mode": "absolute", "absolute": default_threshold("multipath", "analytic"), "hysteresis_count": 2}
    mock, config, url = start_fleet(run_dir, scenario, ids, threshold=fixed)
    gw = start_gateway(config, run_dir)
    def temperature_spread_c() -> float:
        d = open_database(url, upgrade=False)
        try:
            with d.session() as s:
                return s.scalar(select(func.max(MeasurementRow.temperature_c) - func.min(MeasurementRow.temperature_c)))
        finally:
            d.dispose()

    try:
        wait_until(lambda: all(counts(url).get(n, 0) >= 20 for n in ids) and temperature_spread_c() >= 3.0,
                   200, 1.0, what="a 3 degC swing of the pipe temperature, with 20 measurements per node")
    finally:
        gw.close()
        mock.close()
    db = open_database(url, upgrade=False)
    with db.session() as s:
        flagged = s.scalars(select(StateChangeRow).where(StateChangeRow.to_state.in_(["suspected", "damage"]))).all()
        assert flagged == [], [(c.node_id, c.to_state.value) for c in flagged]
        states = {n: s.get(NodeRow, n).state.value for n in ids}
        assert set(states.values()) <= {"ok"}, states
        peaks = s.scalars(select(DetectionRow.peak_di)).all()
        assert max(peaks) < fixed["absolute"]
    db.dispose()


def test_a_decommissioned_node_is_left_alone_until_it_is_recommissioned(run_dir):
    from db.nodes import decommission_node, recommission_node

    ids = ["kept", "retired"]
    mock, config, url = start_fleet(run_dir, write_scenario(run_dir / "s.toml", ids), ids, interval_s=0.3)
    gw = start_gateway(config, run_dir)
    try:
        wait_until(lambda: min(counts(url).get(n, 0) for n in ids) >= 3, 120, 0.3, what="3 measurements per node")
        db = open_database(url, upgrade=False)
        try:
            with db.write() as session:
                decommission_node(session, "retired", who="admin:test", reason="line removed")
            wait_until(lambda: "not polling until it is recommissioned" in gw.stderr, 30, 0.2, what="the gateway noticing")
            frozen = counts(url)["retired"]
            kept = counts(url)["kept"]
            wait_until(lambda: counts(url)["kept"] >= kept + 5, 120, 0.3, what="5 more measurements of the kept node")
            assert counts(url)["retired"] == frozen
            with db.session() as session:
                assert session.get(NodeRow, "retired").online is False
            with db.write() as session:
                recommission_node(session, "retired")
            wait_until(lambda: counts(url)["retired"] >= frozen + 2, 120, 0.3, what="polling again after recommissioning")
            with db.session() as session:  # both changes were told to the alert sinks, once each
                kinds = session.scalars(select(EventRow.kind).where(EventRow.node_id == "retired")
                                        .order_by(EventRow.created_at)).all()
                told = [k for k in kinds if k in ("node_decommissioned", "node_recommissioned")]
            assert told == ["node_decommissioned", "node_recommissioned"]
        finally:
            db.dispose()
        assert "polling again" in gw.stderr
    finally:
        gw.close()
        mock.close()


def test_a_defect_strong_enough_to_leave_a_fifth_of_the_record_is_damage_not_a_blind_node(run_dir):
    # A notch of strength 2 (its scattered amplitude twice the incident at one wavelength) leaves 23 % of
    # the record unexplained by any baseline, beyond the 5 % that a right reference leaves: before
    # 2026-12-03 the gateway read it as no valid baseline (monitoring_blind, a warning).
    (run_dir / "s.toml").write_text(scenario_node("strong", 300, defect=(200.0, 90.0, 30.0), strength=2.0))
    mock, config, url = start_fleet(run_dir, run_dir / "s.toml", ["strong"])
    gw = start_gateway(config, run_dir)
    db = None
    try:
        wait_until(lambda: node_state(url, "strong") == "damage", 150, 0.5, what="the strongly damaged node flagged")
        db = open_database(url, upgrade=False)
        with db.session() as s:
            states = [c.to_state.value for c in s.scalars(
                select(StateChangeRow).where(StateChangeRow.node_id == "strong").order_by(StateChangeRow.id))]
            assert "no_valid_baseline" not in states, states
            last = latest_detection(s, "strong")
            assert last.abstain_reason is None
            assert_near_the_notch(last)
            blind = s.scalars(select(EventRow).where(EventRow.node_id == "strong")).all()
            assert not [e for e in blind if e.kind == "monitoring_blind"]
        assert "strong change" in gw.stderr
    finally:
        if db is not None:
            db.dispose()
        gw.close()
        mock.close()
