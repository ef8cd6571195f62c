"""Gateway pieces in-process: config validation, the watchdog's stall detection, JSON logs, surviving a full disk."""
from __future__ import annotations

import io
import json
import logging
import sqlite3
import subprocess
import sys
import threading
from dataclasses import replace

import pytest
from sqlalchemy import event, func, select

from db.database import open_database
from db.models import MeasurementRow, NodeState
from gateway.assessment import joins_library
from gateway.config import ConfigError, NodeSettings, load_settings
from gateway.logs import node_context, setup_logging
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from mocknode.scenario import NodeScenario
from mocknode.server import MockNodeServer
from tests.support.process_harness import wait_until
from tests.support.synthetic import baseline_and_scatterer

GOOD = """
[database]
url = "sqlite:///{db}"
[[nodes]]
id = "a"
url = "/dev/ttyUSB0"
[[nodes]]
id = "b"
url = "socket://127.0.0.1:7001"
interval_s = 30
[nodes.threshold]
mode = "absolute"
absolute = 0.5
"""


def test_config_loads_with_defaults_and_per_node_overrides(tmp_path):
    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db"))
    s = load_settings(path)
    assert [n.id for n in s.nodes] == ["a", "b"]
    assert s.nodes[0].interval_s == 60.0 and s.nodes[0].threshold.mode == "calibrated"
    assert s.nodes[1].threshold.absolute == 0.5 and s.nodes[1].baud == 230400


def test_environment_overrides_the_file(tmp_path, monkeypatch):
    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db"))
    monkeypatch.setenv("PIPESENTRY_DATABASE__URL", "sqlite:////elsewhere.db")
    monkeypatch.setenv("PIPESENTRY_LOGGING__LEVEL", "DEBUG")
    s = load_settings(path)
    assert s.database.url == "sqlite:////elsewhere.db" and s.logging.level == "DEBUG"


def test_the_modal_filter_is_off_unless_a_node_asks_for_it(tmp_path):
    from gateway.assessment import assess_settings
    from imaging.modal import default_modal_orders

    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db") + '[nodes.imaging]\nmodal_orders = "auto"\n')
    plain, filtered = load_settings(path).nodes
    assert assess_settings(plain, 0.02, 4.0).modal_orders_for(16) is None
    assert assess_settings(filtered, 0.02, 4.0).modal_orders_for(16) == default_modal_orders(16)


def test_a_node_whose_thermometer_is_not_trusted_can_leave_the_stretch_to_the_search(tmp_path):
    from gateway.assessment import assess_settings

    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db") + "[nodes.imaging]\nthermometer = false\n")
    trusted, untrusted = load_settings(path).nodes
    assert assess_settings(trusted, 0.02, 4.0).thermometer is True
    assert assess_settings(untrusted, 0.02, 4.0).thermometer is False


def test_a_record_beyond_the_compensated_temperature_range_is_stored_as_an_abstention_with_its_reason(tmp_path):
    from gateway.assessment import assess_settings, detection_input
    from imaging.pipeline import assess
    from tests.support.synthetic import mock_pipe_record as record

    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db") + "[nodes.imaging]\nmax_compensated_stretch = 0.003\n")
    strict, lenient = load_settings(path).nodes
    warm, library = record(45.0, 2), [record(20.0, 1)]
    abstained = detection_input(assess(warm, library, assess_settings(strict, 0.02, 4.0)),
                                NodeState.NO_VALID_BASELINE, 0.02, [7])
    assert abstained.peak_di is None and "about 2" in abstained.abstain_reason
    assert abstained.baseline_measurement_id is None
    imaged = detection_input(assess(warm, library, assess_settings(lenient, 0.02, 4.0)),
                             NodeState.OK, 0.02, [7])
    assert imaged.peak_di is not None and imaged.abstain_reason is None and imaged.baseline_measurement_id == 7


@pytest.mark.parametrize(
    "body, key",
    [
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\ninterval_s = -1\n', "nodes.0.interval_s"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\n[nodes.imaging]\nmax_compensated_stretch = 0.01\n',
         "nodes.0.imaging.max_compensated_stretch"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\n[nodes.imaging]\nmodal_orders = 9\n', "nodes.0.imaging.modal_orders"),
        ('[[nodes]]\nid = "a b"\nurl = "/dev/x"\n', "nodes.0.id"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\nbaudrate = 9600\n', "nodes.0.baudrate"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\n[nodes.threshold]\nmode = "absolute"\n', "nodes.0.threshold"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\n[[nodes]]\nid = "a"\nurl = "/dev/y"\n', "unique"),
        ('[[nodes]]\nid = "a"\nurl = "/dev/x"\n[[nodes]]\nid = "b"\nurl = "/dev/x"\n', "share a port"),
        ("[database]\nurl = 'x'\n", "nodes"),
        ("[[nodes]\n", "line 1"),
    ],
)
def test_config_errors_name_the_offending_key(tmp_path, body, key):
    path = tmp_path / "g.toml"
    path.write_text(body)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_settings(path)


@pytest.mark.e2e
def test_gateway_refuses_a_bad_config_with_exit_2_and_one_line(tmp_path):
    path = tmp_path / "g.toml"
    path.write_text('[[nodes]]\nid = "a"\nurl = "/dev/x"\ninterval_s = 0\n')
    proc = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "nodes.0.interval_s" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "pipesentry.db").exists()  # nothing was started half-configured


@pytest.mark.e2e
def test_check_validates_without_starting(tmp_path):
    path = tmp_path / "g.toml"
    path.write_text(GOOD.format(db=tmp_path / "x.db"))
    proc = subprocess.run([sys.executable, "-m", "pipesentry", "gateway", "--config", str(path), "--check"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "2 node(s)" in proc.stdout
    assert not (tmp_path / "x.db").exists()


def test_watchdog_sees_a_worker_that_really_hangs():
    beats = Heartbeats()
    release = threading.Event()

    def healthy():
        for _ in range(200):
            beats.beat("healthy")
            if release.wait(0.01):
                return

    def hanging():
        beats.beat("hung")
        release.wait(10)  # stuck: no beat until released

    threads = [threading.Thread(target=healthy), threading.Thread(target=hanging)]
    for t in threads:
        t.start()
    try:
        wait_until(lambda: beats.stalled({"healthy": 0.2, "hung": 0.2}) == ["hung"], 5, 0.02,
                   what="the hung loop to be reported")
    finally:
        release.set()
        for t in threads:
            t.join(5)


def test_json_logs_carry_the_node_id():
    stream = io.StringIO()
    setup_logging("INFO", json_lines=True, stream=stream)
    try:
        log = logging.getLogger("pipesentry.gateway")
        with node_context("node-7"):
            log.info("measurement %d stored", 12, extra={"measurement_id": 12})
        log.info("daemon line")
    finally:
        logging.getLogger().handlers.clear()
    first, second = (json.loads(line) for line in stream.getvalue().splitlines())
    assert first["node"] == "node-7" and first["msg"] == "measurement 12 stored" and first["measurement_id"] == 12
    assert second["node"] == "-"


def test_worker_survives_a_full_disk_and_resumes_when_space_returns(tmp_path, caplog):
    """A real SQLite file whose page budget runs out (PRAGMA max_page_count), then is raised again."""
    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    budget = {"pages": None}

    @event.listens_for(db.engine, "connect")
    def limit_pages(dbapi_conn, _record):
        if budget["pages"] is not None:
            dbapi_conn.execute(f"PRAGMA max_page_count = {budget['pages']}")

    def count():
        with db.session() as s:
            return s.scalar(select(func.count()).select_from(MeasurementRow))

    scn = NodeScenario(node_id="full", seed=5)
    with MockNodeServer([scn]) as server:
        stop = threading.Event()
        worker = NodeWorker(NodeSettings(id="full", url=server.urls["full"], interval_s=0.05, timeout_s=1.0),
                            db, Heartbeats(), stop, backoff_max_s=0.2)
        worker.thread.start()
        try:
            wait_until(lambda: count() >= 2, 60, what="two measurements")
            pages = sqlite3.connect(tmp_path / "g.db").execute("PRAGMA page_count").fetchone()[0]
            budget["pages"] = pages + 2  # far less than one measurement needs
            db.engine.dispose()  # new connections get the budget
            with caplog.at_level(logging.ERROR, logger="pipesentry.gateway"):
                wait_until(lambda: "storage unavailable" in caplog.text, 60, what="a full-disk error")
                stuck = count()
                assert worker.thread.is_alive()
            budget["pages"] = None
            db.engine.dispose()
            wait_until(lambda: count() >= stuck + 2, 60, what="writes to resume")
        finally:
            stop.set()
            worker.thread.join(10)
    con = sqlite3.connect(tmp_path / "g.db")
    assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    con.close()
    assert worker.counters.storage_errors >= 1
    db.dispose()


def _library_at(*temps_c):
    base, _ = baseline_and_scatterer(200, 90, n_rx=2, n_samples=100)
    return [replace(base, temperature_c=t) for t in temps_c]


@pytest.mark.parametrize(
    "change, joins",
    [
        ({}, True),
        ({"temperature_c": 21.0}, False),  # within 2 degC of a library baseline
        ({"peak_di": 0.6}, False),  # not clearly healthy: above half the threshold
        ({"state": "suspected"}, False),
        ({"threshold": None}, False),  # still calibrating
        ({"baseline_age_days": 45.0}, False),  # past the growth window
        ({"temperature_c": float("nan")}, False),
        ({"library": "full"}, False),
    ],
)
def test_a_clearly_healthy_reading_at_a_new_temperature_joins_the_library(change, joins):
    node = NodeSettings(id="n", url="loop://")
    args = dict(state=NodeState.OK, peak_di=0.3, threshold=1.0, temperature_c=25.0,
                library=_library_at(20.0, 22.5), baseline_age_days=3.0)
    args.update(change)
    if isinstance(args["state"], str):
        args["state"] = NodeState(args["state"])
    if args["library"] == "full":
        args["library"] = _library_at(*[100.0 + 3 * k for k in range(node.imaging.library_size)])  # far, but full
    assert joins_library(node, **args) is joins
