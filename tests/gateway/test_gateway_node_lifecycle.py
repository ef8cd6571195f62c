"""The gateway's cycle across node reboots and settings it did not ask for: NodeWorker.poll_once against
the mock node on a real pty, a real SQLite file. The e2e counterpart runs real processes
(test_gateway_node_lifecycle_e2e.py); here the reboot is placed exactly between STATUS and ACQUIRE."""
from __future__ import annotations

import re
import threading
import time

import pytest
from sqlalchemy import select

from db.database import open_database
from db.models import DetectionRow, DiMapRow, EventRow, MapSource, MeasurementRow, NodeRow, NodeState
from gateway.acquisition import SettingsChanged, requested_configuration
from gateway.config import ConfigError, NodeSettings, load_settings
from gateway.node_client import NodeClient
from gateway.record_settings import RecordSettings, comparable, configure_problems, differences
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from mocknode.faults import FaultSpec
from mocknode.scenario import FirmwareSpec, PowerUpSpec, default_scenario
from mocknode.server import MockNodeServer
from protocol.messages import ConfigureReply, ConfigureRequest, InfoReply

pytestmark = pytest.mark.timeout(120)
POWER_UP = PowerUpSpec(averaging=1, n_samples=5000, excitation_hz=60e3)


def power_cycle(server: MockNodeServer) -> None:
    """Reboot the mock node and return once it has (it reboots between requests, in its own thread)."""
    runner = next(iter(server.runners.values()))
    before = runner.reboots
    server.power_cycle()
    deadline = time.monotonic() + 5.0
    while runner.reboots == before:
        assert time.monotonic() < deadline, "the mock node did not reboot"
        time.sleep(0.01)


class RebootBeforeAcquire(NodeClient):
    """The real client; when armed, the node is power-cycled after STATUS and before ACQUIRE."""

    server: MockNodeServer
    armed = threading.Event()

    def acquire(self, baseline: bool, timeout_s: float | None = None):
        if self.armed.is_set():
            self.armed.clear()
            power_cycle(self.server)
        return super().acquire(baseline, timeout_s)


@pytest.fixture
def node(tmp_path, request):
    version = getattr(request, "param", 2)
    base = default_scenario(1).nodes[0]
    scenario = base.model_copy(update={"power_up": POWER_UP, "faults": FaultSpec(protocol_version=version)})
    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    with MockNodeServer([scenario]) as server:
        RebootBeforeAcquire.server = server
        RebootBeforeAcquire.armed.clear()
        settings = NodeSettings(id="node-01", url=server.urls["node-01"], timeout_s=1.0,
                                threshold={"mode": "absolute", "absolute": 0.05})
        worker = NodeWorker(settings, db, Heartbeats(), threading.Event(), client_factory=RebootBeforeAcquire)
        try:
            yield worker, db
        finally:
            worker._close()
            db.dispose()


def rows(db, model, **where):
    with db.session() as s:
        query = select(model)
        for key, value in where.items():
            query = query.where(getattr(model, key) == value)
        return s.scalars(query.order_by(*model.__mapper__.primary_key)).all()


def settings_of(row: MeasurementRow) -> tuple[int, int, float]:
    return row.averaging, row.n_samples, row.excitation_hz


def test_a_record_taken_after_an_unseen_reboot_is_stored_as_the_node_states_and_not_imaged(node):
    worker, db = node
    worker.poll_once()  # commissioning: the baseline
    assert worker.poll_once().peak_di is not None  # imaged against it
    RebootBeforeAcquire.armed.set()
    outcome = worker.poll_once()
    assert outcome.state == NodeState.NO_VALID_BASELINE and outcome.peak_di is None
    stored = rows(db, MeasurementRow)[-1]
    assert settings_of(stored) == (1, 5000, 60e3)  # what the node said, not what the gateway asked for
    reason = rows(db, DetectionRow)[-1].abstain_reason
    assert reason.startswith("settings differ from every baseline's: excitation_hz 60000 (baseline 85000)")
    assert "averaging 1 (baseline 10)" in reason and "n_samples 5000 (baseline 6000)" in reason
    after = worker.poll_once()  # the reboot is noticed: INFO and CONFIGURE again, then imaged again
    assert after.state == NodeState.OK and after.peak_di is not None
    assert settings_of(rows(db, MeasurementRow)[-1]) == (10, 6000, 85e3)
    (node_row,) = rows(db, NodeRow)
    assert node_row.reboots == 1 and node_row.boot_id == rows(db, MeasurementRow)[-1].boot_id
    with db.session() as s:  # the blind record and the recovery were told, in that order
        kinds = s.scalars(select(EventRow.kind).order_by(EventRow.created_at)).all()
    assert kinds[-2:] == ["monitoring_blind", "monitoring_restored"]


@pytest.mark.parametrize("node", [1], indirect=True)
def test_a_version_1_record_after_an_unseen_reboot_is_dropped_and_the_next_is_imaged(node):
    worker, db = node
    worker.poll_once()
    worker.poll_once()
    RebootBeforeAcquire.armed.set()
    with pytest.raises(SettingsChanged, match="does not say what it was taken with"):
        worker.poll_once()
    assert len(rows(db, MeasurementRow)) == 2
    after = worker.poll_once()
    assert after.peak_di is not None and settings_of(rows(db, MeasurementRow)[-1]) == (10, 6000, 85e3)
    assert rows(db, NodeRow)[0].reboots == 1


def test_a_commissioning_record_with_power_up_settings_never_becomes_the_baseline(node):
    worker, db = node
    RebootBeforeAcquire.armed.set()
    with pytest.raises(SettingsChanged, match="not a baseline"):
        worker.poll_once()
    assert rows(db, MeasurementRow) == []
    worker.poll_once()
    (baseline,) = rows(db, MeasurementRow)
    assert settings_of(baseline) == (10, 6000, 85e3)


def test_the_node_map_after_a_reboot_is_made_against_the_record_that_refilled_its_baseline_slot(node):
    worker, db = node
    worker.poll_once()
    worker.poll_once()
    power_cycle(RebootBeforeAcquire.server)  # a reboot STATUS will see
    worker.poll_once()  # re-configured; this record refills the node's baseline slot
    worker.poll_once()
    measurements = rows(db, MeasurementRow)
    with db.session() as s:
        node_maps = s.scalars(select(DiMapRow).where(DiMapRow.source == MapSource.NODE).order_by(DiMapRow.id)).all()
        assert [m.baseline_measurement_id for m in node_maps] == [measurements[0].id, measurements[2].id]
        assert [m.measurement_id for m in node_maps] == [measurements[1].id, measurements[3].id]


def test_a_node_without_on_board_di_or_a_baseline_slot_is_never_asked_for_them(tmp_path):
    scenario = default_scenario(1).nodes[0].model_copy(update={"firmware": FirmwareSpec(capabilities=[])})
    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    with MockNodeServer([scenario]) as server:
        settings = NodeSettings(id="node-01", url=server.urls["node-01"], timeout_s=1.0,
                                threshold={"mode": "absolute", "absolute": 0.05})
        worker = NodeWorker(settings, db, Heartbeats(), threading.Event())
        try:
            for _ in range(3):
                worker.poll_once()
        finally:
            worker._close()
        refused = server.runners["node-01"].node.rejected_requests
    with db.session() as s:
        sources = set(s.scalars(select(DiMapRow.source)).all())
        kinds = [m.kind.value for m in s.scalars(select(MeasurementRow).order_by(MeasurementRow.id))]
    db.dispose()
    assert refused == 0  # no COMPUTE_DI, READ_DI or baseline ACQUIRE it would have had to refuse
    assert sources == {MapSource.GATEWAY} and kinds == ["baseline", "monitor", "monitor"]


# ------------------------------------------------------------------ the pure parts

SETTINGS = RecordSettings(85e3, 5, 10, 16, 6000, 10e6, 0.0)


def test_records_are_comparable_only_with_baselines_of_the_same_settings():
    other = RecordSettings(85e3, 5, 1, 16, 5000, 10e6, 0.0)
    assert comparable(SETTINGS, [other, SETTINGS]) == ([1], None)
    keep, reason = comparable(other, [SETTINGS])
    assert keep == [] and reason.startswith("settings differ from every baseline's: averaging 1 (baseline 10), "
                                            "n_samples 5000 (baseline 6000)")


def test_excitation_is_compared_as_the_float32_the_wire_carries():
    assert differences(RecordSettings(85e3 + 1e-4, 5, 10, 16, 6000, 10e6, 0.0), SETTINGS) == []


def test_a_configured_length_beyond_the_node_is_requested_at_its_limit_and_said_so():
    info = InfoReply("n", 0, 4, 0, 2, 7, 1, 4096, 2048, 16, 10, 10, 4, 1e7, 8000, 400.0, 360.0, 3130.0, 0, 0)
    asked, problems = requested_configuration(NodeSettings(id="n", url="loop://", n_samples=9000), info)
    assert asked.n_samples == 8000 and asked.channel_mask == 0xFFFF
    assert problems == ["n_samples: 9000 configured, the node takes at most 8000; records are 8000 long"]


def test_settings_a_node_applied_differently_are_named():
    asked = ConfigureRequest(85e3, 5, 10, 0xFFFF, 6000)
    assert configure_problems(asked, ConfigureReply(85e3, 5, 10, 0xFFFF, 6000)) == []
    assert configure_problems(asked, ConfigureReply(85e3, 5, 10, 0xFFFF, 4000)) == [
        "n_samples: the node applied 4000, the gateway asked for 6000"]


# ------------------------------------------------------------------ the timeouts docs/protocol.md names

TIMEOUTS = ("shot_period_s = 0.5\ncompute_timeout_s = 1800\nbackoff_s = 0.2\nbackoff_max_s = 5\n"
            "transfer_rounds = 8\ntimeout_s = 3\nretries = 5\n")


def test_the_timeouts_the_protocol_tells_integrators_to_set_reach_the_node_client(tmp_path):
    path = tmp_path / "g.toml"
    path.write_text('[[nodes]]\nid = "a"\nurl = "loop://"\n' + TIMEOUTS)
    node = load_settings(path).nodes[0]
    assert node.client_options() == {"baudrate": 230400, "timeout_s": 3.0, "retries": 5, "backoff_s": 0.2,
                                     "backoff_max_s": 5.0, "shot_period_s": 0.5, "compute_timeout_s": 1800.0,
                                     "transfer_rounds": 8}
    client = NodeClient(node.url, **node.client_options())
    try:
        assert (client.shot_period_s, client.compute_timeout_s, client.transfer_rounds) == (0.5, 1800.0, 8)
    finally:
        client.close()
    # the watchdog's patience grows with them: a 30 min on-board DI is not a hung gateway
    assert node.worst_cycle_s() > 6 * 1800


@pytest.mark.parametrize("line, key", [
    ("compute_timeout_s = inf", "nodes.0.compute_timeout_s"),
    ("compute_timeout_s = nan", "nodes.0.compute_timeout_s"),
    ("compute_timeout_s = 100000", "nodes.0.compute_timeout_s"),
    ("shot_period_s = 0", "nodes.0.shot_period_s"),
    ("shot_period_s = -0.01", "nodes.0.shot_period_s"),
    ("timeout_s = 1e9", "nodes.0.timeout_s"),
    ("transfer_rounds = 65", "nodes.0.transfer_rounds"),
    ("backoff_s = 3\nbackoff_max_s = 1", "backoff_max_s (1.0) is below backoff_s (3.0)"),
])
def test_a_timeout_that_is_not_finite_positive_and_bounded_is_refused_with_its_key(tmp_path, line, key):
    path = tmp_path / "g.toml"
    path.write_text(f'[[nodes]]\nid = "a"\nurl = "loop://"\n{line}\n')
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_settings(path)
