"""Failed cycles: a node whose every cycle fails with its port open is not online, and the gateway's counts
of why are stored; a cycle cut short by the shutdown is logged without a traceback.

The real NodeWorker loop against the mock node on a real pty and a real SQLite file; the failure
is placed in the client (every trace transfer given up on, or the node silent after connecting),
so that each cycle fails the same way. Every wait is bounded.
"""
from __future__ import annotations

import logging
import threading
import time

import pytest

from db.database import open_database
from db.models import NodeRow
from gateway.config import NodeSettings
from gateway.node_client import NodeClient
from gateway.node_errors import NodeTimeout, TransferError
from gateway.watchdog import Heartbeats
from gateway.worker import NodeWorker
from mocknode.scenario import default_scenario
from mocknode.server import MockNodeServer
from tests.support.process_harness import wait_until

pytestmark = pytest.mark.timeout(120)


class TracesNeverArrive(NodeClient):
    """The real client, except that every trace transfer fails as a transfer given up on."""

    def read_traces(self, *args, **kwargs):
        raise TransferError("traces: chunks missing after every retry (injected)")


class SilentAfterConnecting(NodeClient):
    """The real client; after INFO and CONFIGURE the node answers nothing more."""

    def status(self, *args, **kwargs):
        raise NodeTimeout("STATUS: no reply after every retry (injected)")


def stored_node(db) -> NodeRow | None:
    with db.session() as session:
        return session.get(NodeRow, "node-01")


@pytest.mark.parametrize(("client", "counter"), [(TracesNeverArrive, "gateway_transfer_errors"),
                                                 (SilentAfterConnecting, "gateway_timeouts")])
def test_a_node_failing_every_cycle_on_an_open_port_is_offline_with_its_errors_counted(tmp_path, client, counter):
    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    stop = threading.Event()
    with MockNodeServer(default_scenario(1).nodes[:1]) as server:
        settings = NodeSettings(id="node-01", url=server.urls["node-01"], timeout_s=1.0, interval_s=0.2)
        worker = NodeWorker(settings, db, Heartbeats(), stop, backoff_max_s=0.5, client_factory=client)
        worker.thread.start()
        try:
            def failed_twice() -> NodeRow | None:
                node = stored_node(db)
                return node if node is not None and node.error_counters.get(counter, 0) >= 2 else None

            node = wait_until(failed_twice, 30, 0.1, what=f"{counter} stored twice")
        finally:
            stop.set()
            worker.thread.join(15)
            db.dispose()
    print(f"failed cycles: {node.error_counters.get('gateway_failures')} stored, {counter} = "
          f"{node.error_counters[counter]}, online = {node.online}")
    assert node.online is False
    assert node.error_counters["gateway_failures"] >= node.error_counters[counter] >= 2


class SignalsItsTransfer(NodeClient):
    """The real client; tells the test when a trace transfer has begun."""

    in_transfer = threading.Event()

    def read_traces(self, *args, **kwargs):
        self.in_transfer.set()
        time.sleep(0.2)  # the daemon's shutdown closes the port while the transfer runs
        return super().read_traces(*args, **kwargs)


def test_a_shutdown_that_closes_the_port_mid_transfer_logs_no_traceback(tmp_path, caplog):
    """What Gateway.shutdown does to a worker stuck in a transfer: stop set, then its port closed."""
    db = open_database(f"sqlite:///{tmp_path / 'g.db'}")
    stop = threading.Event()
    SignalsItsTransfer.in_transfer.clear()
    with MockNodeServer(default_scenario(1).nodes[:1]) as server, caplog.at_level(logging.INFO, "pipesentry"):
        settings = NodeSettings(id="node-01", url=server.urls["node-01"], timeout_s=1.0, interval_s=0.2)
        worker = NodeWorker(settings, db, Heartbeats(), stop, client_factory=SignalsItsTransfer)
        worker.thread.start()
        try:
            assert SignalsItsTransfer.in_transfer.wait(30), "no transfer began"
            stop.set()
            worker.conn.client.close()
            worker.thread.join(15)
        finally:
            stop.set()
            db.dispose()
    assert not worker.thread.is_alive()
    # Neither a traceback nor a warning of a port that "vanished": the port was closed on purpose.
    assert [r.getMessage() for r in caplog.records if r.exc_info or r.levelno >= logging.WARNING] == []
    assert any("cycle in flight was abandoned" in r.getMessage() for r in caplog.records)
