"""The gateway daemon: one worker per node, retention, signals, systemd readiness and watchdog."""
from __future__ import annotations

import logging
import signal
import threading
import time
from datetime import timedelta
from typing import Any

from alerts.delivery import AlertDelivery
from alerts.events import storage_unavailable_event
from db.clock import utc_now
from db.database import Database, StorageOutage, open_database
from db.errors import DatabaseDamaged, ForeignDatabase, SchemaOutOfDate, StorageError
from db.measurements import add_event_once
from db.nodes import register_configured_node
from db.retention import prune_traces
from db.uplink_queue import QueuePolicy, queue_stats, store_policy
from db.urls import safe_database_url
from gateway.clock import STEP_TOLERANCE_S, Clock, ElapsedWall, SystemClock
from gateway.config import GatewaySettings
from gateway.metrics import MetricsServer, gateway_registry, serve_metrics
from gateway.readiness import readiness_report
from gateway.uplink.sender import UplinkKeyError, UplinkSender
from gateway.watchdog import Heartbeats, sd_notify, watchdog_interval_s
from gateway.worker import NodeWorker

log = logging.getLogger("pipesentry.gateway")

RETENTION = "retention"
STORAGE = "storage"
STORAGE_TICK_S = 5.0  # how often the storage loop looks for an ended outage to tell


class Gateway:
    """Owns the database, the node workers and the retention loop."""

    def __init__(self, settings: GatewaySettings, db: Database, *, clock: Clock | None = None) -> None:
        self.settings = settings
        self.db = db
        self.clock: Clock = clock or SystemClock()
        self.retention_clock = ElapsedWall(self.clock)  # retention's now: never ahead of the elapsed time
        self.stop = threading.Event()
        self.heartbeats = Heartbeats()
        # The uplink: every write from here on queues what it stores, before any worker writes.
        self.uplink: UplinkSender | None = None
        self.queue_policy = None if settings.uplink is None else QueuePolicy(settings.uplink.send)
        db.queue_uplink(self.queue_policy)
        if settings.uplink is not None:
            self.uplink = UplinkSender(settings.uplink, db, stop=self.stop, heartbeats=self.heartbeats)
        self.workers = [
            NodeWorker(
                node, db, self.heartbeats, self.stop, backoff_max_s=settings.reopen_backoff_max_s,
                alerting=settings.alerting, clock=self.clock,
            )
            for node in settings.nodes
        ]
        self._retention = threading.Thread(target=self._retention_loop, name=RETENTION, daemon=True)
        self._storage = threading.Thread(target=self._storage_loop, name=STORAGE, daemon=True)
        self._untold_outages: list[StorageOutage] = []
        # Alert delivery: one thread per sink plus the outage watcher; none of them waits on a node or on each other.
        self.alerting = AlertDelivery(settings.alerting, db, stop=self.stop, heartbeats=self.heartbeats)
        self.metrics_registry = gateway_registry(self.workers, self.alerting.sink_workers, db, self.uplink)
        self.metrics: MetricsServer | None = None

    def stall_limits_s(self) -> dict[str, float]:
        """How long each loop may go without a beat before the watchdog pings stop."""
        fixed = self.settings.watchdog_stall_s
        limits = {}
        for w in self.workers:
            node = w.settings
            # A full cycle: several commands with retries, a bulk transfer, a wait between cycles.
            cycle_s = node.worst_cycle_s() + self.settings.reopen_backoff_max_s
            limits[w.name] = fixed or 3 * cycle_s
        limits[RETENTION] = fixed or 3 * self.settings.retention.prune_every_s + 600
        limits[STORAGE] = fixed or 3 * STORAGE_TICK_S + 3600  # a quick_check of a large file takes minutes
        limits.update({name: fixed or limit for name, limit in self.alerting.stall_limits_s().items()})
        if self.uplink is not None:
            limits[self.uplink.thread.name] = fixed or self.uplink.stall_limit_s()
        return limits

    def threads(self) -> list[threading.Thread]:
        uplink = [self.uplink.thread] if self.uplink is not None else []
        return [w.thread for w in self.workers] + [self._retention, self._storage] + self.alerting.threads + uplink

    def readiness(self) -> tuple[bool, dict[str, Any]]:
        """``/readyz``: every loop alive, and the uplink's oldest unsent record younger than ``ready_lag_s``."""
        if self.uplink is None:
            return readiness_report(dead_loops=self.dead_loops(), now=utc_now())
        with self.db.session() as session:
            queue = queue_stats(session)
        return readiness_report(dead_loops=self.dead_loops(), now=utc_now(), queue=queue, sender=self.uplink.stats,
                                ready_lag_s=self.uplink.settings.ready_lag_s)

    def dead_loops(self) -> list[str]:
        """Loops whose thread ended while the daemon runs (a bug escaped its loop): nothing polls there any more."""
        return sorted(t.name for t in self.threads() if t.ident is not None and not t.is_alive())

    def register_nodes(self) -> list[str]:
        """Every configured node gets its row before any is polled (never seen until it answers), so a
        node that never answers is listed, counted and reported offline; returns the ones new here.
        A storage error leaves it to the worker, at the node's first failed cycle or first answer.

        The same transaction stores whether this gateway replicates (``uplink_config``), so the
        gateway's API queues an operator's changes exactly when there is an uplink."""
        now = utc_now()
        try:
            with self.db.write() as session:
                store_policy(session, self.queue_policy, now=now)
                added = [node.id for node in self.settings.nodes
                         if register_configured_node(session, node.id, port_url=node.url, now=now)]
        except StorageError as exc:
            log.error("could not register the configured nodes (each is registered when it is polled) nor store "
                      "whether the uplink replicates the API's changes: %s", exc)
            return []
        if added:
            log.info("registered %d configured node(s) not seen yet: %s", len(added), ", ".join(added))
        return added

    def start(self) -> None:
        self.register_nodes()
        for w in self.workers:
            w.thread.start()
        self._retention.start()
        self._storage.start()
        self.alerting.start()
        if self.uplink is not None:
            self.uplink.thread.start()
        self.metrics = serve_metrics(self.settings.metrics, self.metrics_registry, self.readiness)

    def _retention_loop(self) -> None:
        r = self.settings.retention
        self.heartbeats.beat(RETENTION)
        stepped = False
        while not self.stop.is_set():
            try:
                step_s = self.retention_clock.step_s()
                if abs(step_s) > STEP_TOLERANCE_S and not stepped:
                    log.warning("wall clock stepped %+.0f s against the elapsed time since the start: retention "
                                "goes by the elapsed time (a step forward prunes nothing early)", step_s)
                stepped = abs(step_s) > STEP_TOLERANCE_S
                pruned = prune_traces(self.db.write, timedelta(days=r.raw_traces_days), r.prune_batch,
                                      now=self.retention_clock.now())
                if pruned:
                    log.info("retention: pruned the raw traces of %d measurements", pruned)
            except StorageError as exc:
                log.error("retention failed, will retry: %s", exc)
            except Exception:
                log.exception("retention failed unexpectedly, will retry")
            self.heartbeats.beat(RETENTION)
            self.stop.wait(r.prune_every_s)

    def _storage_loop(self) -> None:
        """The database's health: ``quick_check`` every ``integrity_check_every_s`` (measured on the monotonic
        clock), and a ``storage_unavailable`` event for each outage once writes fit again."""
        every_s = self.settings.database.integrity_check_every_s
        monotonic = self.clock.monotonic
        checked_at = monotonic()  # open_database checked it at the start
        self.heartbeats.beat(STORAGE)
        while not self.stop.wait(STORAGE_TICK_S):
            try:
                self._tell_ended_outages()
                if monotonic() - checked_at >= every_s and self.db.damage is None:
                    checked_at = monotonic()
                    damage = self.db.check_integrity()
                    if damage is not None:
                        log.error("integrity check: %s", damage)
            except StorageError as exc:
                log.error("storage check failed, will retry: %s", exc)
            self.heartbeats.beat(STORAGE)

    def _tell_ended_outages(self) -> None:
        """Each ended outage as an event; one that cannot be written yet is kept to be told next tick."""
        self._untold_outages += self.db.take_ended_outages()
        while self._untold_outages:
            outage = self._untold_outages[0]
            assert outage.ended_at is not None  # an ended outage has its end
            event = storage_unavailable_event(self.settings.alerting, since=outage.since, until=outage.ended_at,
                                              failed_writes=outage.failed_writes, reason=outage.reason)
            with self.db.write() as session:
                add_event_once(session, event, node_id=None)
            self._untold_outages.pop(0)

    def shutdown(self, timeout_s: float) -> None:
        """Stop the loops; a worker stuck in a transfer has its port closed to break out."""
        self.stop.set()
        deadline = time.monotonic() + timeout_s * 0.6
        for w in self.workers:
            w.thread.join(max(0.0, deadline - time.monotonic()))
        for w in self.workers:
            if w.thread.is_alive() and w.conn is not None:
                try:
                    w.conn.client.close()  # the blocked read fails at once; the write in flight rolls back
                except OSError as exc:  # a port that vanished meanwhile has nothing left to release
                    log.debug("closing %s at shutdown: %s", w.name, exc)
        deadline = time.monotonic() + timeout_s * 0.3
        for w in self.workers:
            w.thread.join(max(0.0, deadline - time.monotonic()))
        self._retention.join(max(0.0, deadline - time.monotonic()))
        self._storage.join(max(0.0, deadline - time.monotonic()))
        self.alerting.join(max(0.0, deadline - time.monotonic()))
        if self.uplink is not None:  # a request in flight ends by its timeout; its batch is re-sent next start
            self.uplink.thread.join(max(0.0, deadline - time.monotonic()))
        if self.metrics is not None:
            self.metrics.close()
        self.db.dispose()


def _log_loop_death(args: threading.ExceptHookArgs) -> None:
    """A loop's thread ended by an exception: into the log with its traceback (not only bare stderr)."""
    name = args.thread.name if args.thread is not None else "?"
    exc_info = (args.exc_type, args.exc_value, args.exc_traceback) if args.exc_value is not None else None
    log.critical("loop %s died: %s", name, args.exc_type.__name__, exc_info=exc_info)


EXIT_LOOP_DIED = 1  # a supervisor (systemd Restart=always, a container's restart policy) starts it again
EXIT_DATABASE_UNUSABLE = 2  # the database cannot be used as it is (damaged, not SQLite, not writable, other schema)


def run(settings: GatewaySettings) -> int:
    """Run until SIGTERM/SIGINT (exit 0), or until a loop's thread dies (exit 1, after a clean shutdown).

    The signal handlers come first: a stop asked for while the database is opened (an upgrade of a
    large file can take minutes) lets that finish, then exits 0 before any node is polled, instead of
    the interpreter's default of dying mid-upgrade.
    """
    signalled = threading.Event()

    def on_signal(signum, _frame):
        log.info("received %s, shutting down", signal.Signals(signum).name)
        signalled.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    shown = safe_database_url(settings.database.url)
    try:
        db = open_database(settings.database.url, upgrade=True, check_integrity=True)
    except SchemaOutOfDate as exc:
        log.error("database schema cannot be used: %s", exc)
        return EXIT_DATABASE_UNUSABLE
    except DatabaseDamaged as exc:
        log.error("database %s is damaged, not opened (restore it from a backup, docs/storage.md): %s", shown, exc)
        return EXIT_DATABASE_UNUSABLE
    except ForeignDatabase as exc:
        log.error("database %s is not PipeSentry's: %s", shown, exc)
        return EXIT_DATABASE_UNUSABLE
    except StorageError as exc:
        log.error("database %s cannot be opened: %s: %s", shown, type(exc).__name__, exc)
        return EXIT_DATABASE_UNUSABLE
    try:
        gateway = Gateway(settings, db)
    except UplinkKeyError as exc:  # the key file went away since --check
        log.error("uplink: %s", exc)
        db.dispose()
        return 2  # as for any config error
    if signalled.is_set():  # asked to stop while the database was being opened: nothing started yet
        db.dispose()
        log.info("gateway stopped before polling any node")
        return 0
    threading.excepthook = _log_loop_death
    gateway.start()
    log.info("gateway started: %d node(s), database %s", len(gateway.workers), shown)
    sd_notify("READY=1\nSTATUS=polling nodes")
    ping_s = watchdog_interval_s(default_s=5.0)
    limits = gateway.stall_limits_s()
    stalled_reported: list[str] = []
    exit_code = 0
    while not signalled.wait(ping_s):
        if db.damage is not None:
            log.error("database %s found damaged while running, shutting down without writing into it "
                      "(restore it from a backup, docs/storage.md): %s", shown, db.damage)
            exit_code = EXIT_DATABASE_UNUSABLE
            break
        dead = gateway.dead_loops()
        if dead:
            # Its heartbeat would only go stale after the stall limit (hours, or never); the daemon is broken now.
            log.error("loop %s died (see the error above): no watchdog ping, shutting down to be restarted",
                      ", ".join(dead))
            exit_code = EXIT_LOOP_DIED
            break
        stalled = gateway.heartbeats.stalled(limits)
        if stalled:
            if stalled != stalled_reported:
                log.error("no progress in %s: watchdog pings stopped", ", ".join(stalled))
                stalled_reported = stalled
            continue
        stalled_reported = []
        sd_notify("WATCHDOG=1")
    sd_notify("STOPPING=1")
    gateway.shutdown(settings.shutdown_timeout_s)
    log.info("gateway stopped")
    return exit_code
