"""The API's /metrics collector over a real SQLite file: what it says about nodes in each state."""
from __future__ import annotations

from db.database import Database
from db.models import NodeRow, NodeState
from db.records import DetectionInput, StateChangeInput
from tests.support.api_fixtures import api_metrics_text
from tests.support.db_fixtures import ALARM, T0, minutes, store_sample


def test_a_node_calibrating_after_a_new_baseline_has_no_threshold_series(sqlite_db: Database):
    with sqlite_db.write() as session:
        store_sample(session, "node-a", detection=ALARM,
                     state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.DAMAGE))
    assert 'pipesentry_node_di_threshold{node="node-a"} 0.3' in api_metrics_text(sqlite_db)
    with sqlite_db.write() as session:
        # Re-baselined: the first readings calibrate again; the stored threshold is the old baseline's.
        session.get(NodeRow, "node-a").state = NodeState.CALIBRATING
    text = api_metrics_text(sqlite_db)
    assert 'pipesentry_node_di_threshold{node="node-a"}' not in text
    assert 'pipesentry_node_state{node="node-a",state="calibrating"} 1.0' in text


def test_a_calibrating_reading_has_a_peak_but_no_threshold(sqlite_db: Database):
    calibrating = DetectionInput(peak_di=0.01, threshold=None, state=NodeState.CALIBRATING)
    with sqlite_db.write() as session:
        store_sample(session, "node-a", acquired_at=T0 + minutes(1), detection=calibrating,
                     state_change=StateChangeInput(NodeState.COMMISSIONING, NodeState.CALIBRATING))
    text = api_metrics_text(sqlite_db)
    assert 'pipesentry_node_di_peak{node="node-a"} 0.01' in text
    assert "pipesentry_node_di_threshold{" not in text
