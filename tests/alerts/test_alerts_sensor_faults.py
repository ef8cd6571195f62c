"""Sensor fault alerts: raised and cleared on transitions only, debounced, restart-proof, in the measurement's transaction."""
from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client import CollectorRegistry, generate_latest
from pydantic import ValidationError
from sqlalchemy import func, select

from alerts.config import AlertingSettings
from alerts.events import EventKind
from alerts.metrics import SensorFaultCollector
from alerts.sensor_faults import ReceiverTransitions, check_sensor_faults, open_sensor_faults, receiver_transitions
from db.database import open_database
from db.models import DeliveryRow, EventRow, MeasurementRow, NodeState
from db.records import DetectionInput
from tests.support.alerts_fixtures import alerting, dead_receiver
from tests.support.db_fixtures import T0, minutes, store_sample

pytestmark = pytest.mark.timeout(60)


# ------------------------------------------------------------------ the pure transition rule
def test_a_receiver_faulty_in_n_consecutive_measurements_raises_once_and_persisting_raises_nothing():
    assert receiver_transitions([set(), {5}], open_faults=set(), count=2) == ReceiverTransitions()
    assert receiver_transitions([set(), {5}, {5}], open_faults=set(), count=2) == ReceiverTransitions(raised=(5,))
    assert receiver_transitions([{5}, {5}, {5}], open_faults={5}, count=2) == ReceiverTransitions()


def test_an_open_fault_clears_after_n_consecutive_healthy_measurements():
    assert receiver_transitions([{5}, set()], open_faults={5}, count=2) == ReceiverTransitions()
    assert receiver_transitions([{5}, set(), set()], open_faults={5}, count=2) == ReceiverTransitions(cleared=(5,))


def test_a_flapping_receiver_neither_raises_nor_clears():
    flapping = [{5}, set(), {5}, set(), {5}, set()]
    for end in range(1, len(flapping) + 1):
        assert receiver_transitions(flapping[:end], open_faults=set(), count=2) == ReceiverTransitions()
        assert receiver_transitions(flapping[:end], open_faults={5}, count=2) == ReceiverTransitions()


def test_fewer_measurements_than_the_count_decide_nothing_and_a_count_of_one_decides_at_once():
    assert receiver_transitions([{3}], open_faults=set(), count=2) == ReceiverTransitions()
    assert receiver_transitions([set()], open_faults={3}, count=2) == ReceiverTransitions()
    assert receiver_transitions([{3}], open_faults={1}, count=1) == ReceiverTransitions(raised=(3,), cleared=(1,))


def test_receivers_are_judged_independently():
    change = receiver_transitions([{1, 2}, {2, 3}, {2, 3, 4}], open_faults={1, 2}, count=2)
    assert change == ReceiverTransitions(raised=(3,), cleared=(1,))


def test_a_count_below_one_is_refused_in_the_rule_and_in_the_settings():
    with pytest.raises(ValueError, match="at least 1"):
        receiver_transitions([{1}], open_faults=set(), count=0)
    with pytest.raises(ValidationError, match="sensor_fault_count"):
        AlertingSettings.model_validate({"sensor_fault_count": 0})
    assert AlertingSettings().sensor_fault_count == 2


# ------------------------------------------------------------------ through the database, as the gateway does
SINKS = ({"type": "webhook", "name": "hook", "url": "http://127.0.0.1:9/", "secret": "whsec_" + "QUJD" * 8},
         {"type": "slack", "name": "chat", "url": "http://127.0.0.1:9/x", "min_severity": "critical"})


class Gateway:
    """Stores monitor measurements as gateway/worker.py does: detection, then the sensor fault check, one transaction."""

    def __init__(self, url: str, settings: AlertingSettings) -> None:
        self.url = url
        self.settings = settings
        self.database = open_database(url)
        self.seed = 0

    def measure(self, *faults: dict, crash: bool = False) -> list:
        self.seed += 1
        detection = DetectionInput(peak_di=0.1, threshold=0.3, state=NodeState.OK, sensor_faults=list(faults))
        with self.database.write() as session:
            row = store_sample(session, "node-a", acquired_at=T0 + minutes(self.seed), seed=self.seed,
                               detection=detection)
            events = check_sensor_faults(session, self.settings, node_id="node-a", measurement_id=row.id,
                                         faults=detection.sensor_faults, state="ok")
            if crash:
                raise RuntimeError("power lost before the commit")
        return [(e.kind, e.payload["receiver"]["rx_index"]) for e in events]

    def restart(self) -> None:
        self.database.dispose()
        self.database = open_database(self.url)

    def events(self) -> list[EventRow]:
        with self.database.session() as session:
            return list(session.scalars(select(EventRow).order_by(EventRow.created_at)).all())


@pytest.fixture
def gateway(tmp_path: Path) -> Iterator[Gateway]:
    g = Gateway(f"sqlite:///{tmp_path / 'faults.db'}", alerting(*SINKS))
    yield g
    g.database.dispose()


def test_a_dead_receiver_raises_after_two_measurements_and_clears_after_two_healthy_ones(gateway):
    dead = dead_receiver(5)
    assert gateway.measure() == []
    assert gateway.measure(dead) == []  # once could be a glitch
    assert gateway.measure(dead) == [(EventKind.SENSOR_FAULT, 5)]
    assert gateway.measure(dead) == []  # still faulty: nothing new
    assert gateway.measure() == []
    assert gateway.measure() == [(EventKind.SENSOR_FAULT_CLEARED, 5)]
    assert gateway.measure() == []

    raised, cleared = gateway.events()
    p = raised.payload
    assert raised.kind == "sensor_fault" and raised.severity == "warning" and raised.node_id == "node-a"
    assert p["receiver"] == {"rx_index": 5, "rx_angle_deg": 112.5, "kind": "no_signal", "amplitude_ratio": 0.03,
                             "delay_s": 0.0}
    assert p["faulty_receivers"] == [5] and p["consecutive_measurements"] == 2 and p["measurement_id"] == 3
    assert p["links"]["measurement"] == "http://127.0.0.1:8000/api/v1/measurements/3"
    assert "receiver 5 (112 deg) faulty: no signal (direct arrival at 3% of baseline)" in p["summary"]
    q = cleared.payload
    assert cleared.severity == "info" and q["raised_event_id"] == str(raised.id) and q["raised_measurement_id"] == 3
    assert q["receiver"] == p["receiver"] and q["faulty_receivers"] == [] and q["measurement_id"] == 6
    # The clearing goes wherever the fault went (routed as warning): the critical-only chat gets neither.
    with gateway.database.session() as session:
        sinks = session.execute(select(DeliveryRow.event_id, DeliveryRow.sink)).all()
    assert sorted(sinks) == sorted([(raised.id, "hook"), (cleared.id, "hook")])


def test_a_restart_neither_raises_an_open_fault_again_nor_loses_its_clearing(gateway):
    dead = dead_receiver(2, kind="amplitude")
    gateway.measure(dead)
    gateway.restart()
    assert gateway.measure(dead) == [(EventKind.SENSOR_FAULT, 2)]  # the streak survived the restart
    gateway.restart()
    assert gateway.measure(dead) == []
    gateway.measure()
    gateway.restart()
    assert gateway.measure() == [(EventKind.SENSOR_FAULT_CLEARED, 2)]
    gateway.restart()
    assert gateway.measure() == [] and gateway.measure() == []
    assert [e.kind for e in gateway.events()] == ["sensor_fault", "sensor_fault_cleared"]


def test_a_crash_before_the_commit_loses_the_measurement_and_its_event_together(gateway):
    dead = dead_receiver(4)
    gateway.measure(dead)
    with pytest.raises(RuntimeError, match="power lost"):
        gateway.measure(dead, crash=True)
    assert gateway.events() == []
    with gateway.database.session() as session:
        assert session.scalar(select(func.count()).select_from(MeasurementRow)) == 1
    gateway.restart()
    assert gateway.measure(dead) == [(EventKind.SENSOR_FAULT, 4)]


def test_several_receivers_each_get_their_own_alert_and_a_fault_raised_again_gets_a_new_id(gateway):
    a, b = dead_receiver(1), dead_receiver(6, kind="timing")
    gateway.measure(a)
    assert gateway.measure(a, b) == [(EventKind.SENSOR_FAULT, 1)]
    assert gateway.measure(b) == [(EventKind.SENSOR_FAULT, 6)]
    assert gateway.measure(b) == [(EventKind.SENSOR_FAULT_CLEARED, 1)]
    with gateway.database.session() as session:
        assert sorted(open_sensor_faults(session, "node-a")) == [6]
    gateway.measure(a, b)
    assert gateway.measure(a, b) == [(EventKind.SENSOR_FAULT, 1)]
    raised_1 = [e for e in gateway.events() if e.kind == "sensor_fault" and e.payload["receiver"]["rx_index"] == 1]
    assert len({e.id for e in raised_1}) == 2
    assert raised_1[-1].payload["faulty_receivers"] == [1, 6]


def test_the_debounce_count_comes_from_the_alerting_settings(gateway):
    gateway.settings = alerting(*SINKS, sensor_fault_count=3)
    dead = dead_receiver(0)
    assert [gateway.measure(dead) for _ in range(3)] == [[], [], [(EventKind.SENSOR_FAULT, 0)]]
    assert gateway.events()[0].payload["consecutive_measurements"] == 3


def test_the_faulty_receivers_gauge_counts_open_alerts_per_node(gateway):
    registry = CollectorRegistry(auto_describe=False)
    registry.register(SensorFaultCollector(lambda: gateway.database))
    with gateway.database.write() as session:
        store_sample(session, "node-b", seed=99)

    def gauge() -> dict[str, float]:
        text = generate_latest(registry).decode()
        return {m[0]: float(m[1]) for m in re.findall(r'^pipesentry_node_faulty_receivers\{node="([^"]+)"\} (\S+)$', text, re.MULTILINE)}

    gateway.measure()
    assert gauge() == {"node-a": 0.0, "node-b": 0.0}
    gateway.measure(dead_receiver(1), dead_receiver(2))
    assert gauge() == {"node-a": 0.0, "node-b": 0.0}, "not before the alert is raised"
    gateway.measure(dead_receiver(1), dead_receiver(2))
    assert gauge() == {"node-a": 2.0, "node-b": 0.0}
    gateway.measure(dead_receiver(2))
    gateway.measure(dead_receiver(2))
    assert gauge() == {"node-a": 1.0, "node-b": 0.0}
