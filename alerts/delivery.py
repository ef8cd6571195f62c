"""The delivery worker: one thread per sink sends the outbox to it; one thread watches for outages and baseline changes.

A sink that is down, slow or gone only ever holds up its own thread, never measurement,
storage or the other sinks. Per sink and node, events go out in the order they were
created: a node's next event waits until the one before it is delivered or dead. Each
attempt is bounded by the sink's timeout; failures are retried with exponential backoff
and full jitter (at least the receiver's Retry-After), up to ``max_attempts`` tries, after
which the delivery is dead (``alerts.outbox.dead_count``). HTTP 410 Gone disables the sink
for its configured endpoint: recorded as a ``sink_disabled`` event (told to the other
sinks); its pending deliveries die, until the endpoint in the config changes.
"""
from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Protocol

from alerts.alertmanager import AlertmanagerTransport
from alerts.backoff import retry_delay_s
from alerts.baseline_watch import check_baseline_changes
from alerts.config import (
    AlertingSettings,
    AlertmanagerSinkSettings,
    AnySinkSettings,
    MqttSinkSettings,
    SlackSinkSettings,
    WebhookSinkSettings,
    sink_secrets,
)
from alerts.errors import DeliveryFailed, EndpointGone
from alerts.events import EventKind, log_level, sink_disabled_event
from alerts.mqtt import MqttTransport
from alerts.outages import check_outages
from alerts.outbox import (
    OutboxEvent,
    claim,
    events_of_kind,
    is_due,
    kill_pending,
    mark_delivered,
    mark_failed,
    pending_heads,
)
from alerts.slack import SlackTransport
from alerts.webhook import WebhookTransport
from db.clock import utc_now
from db.database import Database
from db.errors import StorageError
from db.log_text import mask_secret
from db.measurements import add_event_once

log = logging.getLogger("pipesentry.alerts")

MAX_ATTEMPTS_PER_PASS = 20  # keeps heartbeats regular when many nodes have something due
LEASE_MARGIN_S = 1.0
WATCH = "alerts-watch"


class SinkTransport(Protocol):
    """What a sink module provides: one bounded attempt per event, and upkeep between events."""

    def send(self, item: OutboxEvent) -> None:
        """Deliver ``item`` once; raise DeliveryFailed (retry) or EndpointGone (disable)."""

    def maintain(self) -> None:
        """Periodic upkeep (Alertmanager re-sends active alerts); must not raise."""

    def endpoint_fingerprint(self) -> str:
        """A digest of the configured endpoint (a 410 disables this endpoint, not the name)."""

    def close(self) -> None:
        """Release connections."""


@dataclass
class SinkStats:
    """What one sink's thread did since the process started (the gateway's metrics read it)."""

    attempts: int = 0  # outbox deliveries tried (Alertmanager's periodic re-sends are not counted)
    failures: int = 0  # of which failed (timeout, refused, 5xx, 410, ...)
    last_delivered_at: datetime | None = None  # when a receiver last acknowledged a delivery


class Beats(Protocol):
    def beat(self, name: str) -> None: ...


def make_transport(sink: AnySinkSettings, alerting: AlertingSettings, database: Database) -> SinkTransport:
    """The transport for one configured sink (Alertmanager and MQTT also read the database: what is active).

    Its secrets are masked in every log line and stored error from now on (db/log_text.py)."""
    mask_secret(*sink_secrets(sink))
    if isinstance(sink, WebhookSinkSettings):
        return WebhookTransport(sink)
    if isinstance(sink, AlertmanagerSinkSettings):
        return AlertmanagerTransport(sink, database, api_base_url=alerting.api_base_url)
    if isinstance(sink, SlackSinkSettings):
        return SlackTransport(sink)
    if isinstance(sink, MqttSinkSettings):
        return MqttTransport(sink, alerting, database)
    raise TypeError(f"no transport for sink type {type(sink).__name__}")


def lease_s(sink: AnySinkSettings) -> float:
    """How long a claim holds: the longest one attempt can take (MQTT: connect + PUBACK), plus a margin."""
    return 2 * sink.timeout_s + LEASE_MARGIN_S


class SinkWorker:
    """Sends one sink's outbox, oldest first per node, until ``stop`` is set."""

    def __init__(
        self,
        alerting: AlertingSettings,
        sink: AnySinkSettings,
        transport: SinkTransport,
        database: Database,
        *,
        stop: threading.Event,
        heartbeats: Beats | None = None,
        rng: random.Random | None = None,
        clock: Callable[[], datetime] = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.alerting = alerting
        self.sink = sink
        self.transport = transport
        self.database = database
        self.stop = stop
        self.heartbeats = heartbeats
        self.rng = rng or random.Random()
        self.clock = clock
        self.monotonic = monotonic
        # Retries this process scheduled, by delivery id: when their wait ends on the monotonic
        # clock. The stored wall-clock time serves after a restart; a wall-clock step back must
        # not hold a retry back (issue 15: schedules measure intervals on a monotonic clock).
        self.retry_deadlines: dict[int, float] = {}
        self.disabled = False
        self.stats = SinkStats()
        self.thread = threading.Thread(target=self.run, name=f"alerts-{sink.name}", daemon=True)

    @property
    def name(self) -> str:
        return self.thread.name

    def stall_limit_s(self) -> float:
        """Longest a healthy pass can take: every attempt of a full pass timing out, plus slack."""
        return 3 * (self.alerting.poll_interval_s + MAX_ATTEMPTS_PER_PASS * lease_s(self.sink)) + 60.0

    def run(self) -> None:
        try:
            _loop(self.name, self.run_once, stop=self.stop, heartbeats=self.heartbeats,
                  retry_s=self.alerting.poll_interval_s)
        finally:
            self.transport.close()

    def run_once(self) -> float:
        """One pass: attempt what is due (bounded), do upkeep; return seconds until the next pass."""
        if self.disabled or self._endpoint_disabled():
            self.disabled = True
            self._kill_pending_of_disabled_sink()
            return self.alerting.poll_interval_s
        with self.database.session() as session:
            heads = pending_heads(session, self.sink.name)
        now = self.clock()
        live = {item.delivery_id for item in heads}  # delivered or dead elsewhere: forget its deadline
        self.retry_deadlines = {k: v for k, v in self.retry_deadlines.items() if k in live}
        attempted = 0
        for item in heads:
            if self.stop.is_set() or self.disabled or attempted >= MAX_ATTEMPTS_PER_PASS:
                break
            if is_due(item, now):
                attempted += self.attempt(item)
            elif self._overdue(item, now):
                attempted += self.attempt(item, overdue=True)
        if not self.disabled:
            self.transport.maintain()
        if attempted:
            return 0.0  # a delivered head lets the node's next event through: look again at once
        upcoming = [i.next_attempt_at for i in heads if i.next_attempt_at is not None and i.next_attempt_at > now]
        wait_s = self.alerting.poll_interval_s
        if upcoming:
            wait_s = min(wait_s, max(0.0, (min(upcoming) - self.clock()).total_seconds()))
        return wait_s

    def horizon_s(self) -> float:
        """No wait this sink sets is longer: a stored retry time further ahead is a clock step."""
        return max(self.sink.backoff_cap_s, self.sink.retry_after_max_s, lease_s(self.sink)) + LEASE_MARGIN_S

    def _overdue(self, item: OutboxEvent, now: datetime) -> bool:
        """Not due by its stored time, yet due: its wait ended on this process's monotonic clock,
        or the stored time lies beyond any wait we set (the wall clock went back)."""
        deadline = self.retry_deadlines.get(item.delivery_id)
        if deadline is not None and self.monotonic() >= deadline:
            return True
        return is_due(item, now, horizon_s=self.horizon_s())

    def attempt(self, item: OutboxEvent, *, overdue: bool = False) -> int:
        """Claim, send, record. Returns 1 if an attempt was made, 0 if the claim was lost."""
        now = self.clock()
        self.retry_deadlines.pop(item.delivery_id, None)
        with self.database.write() as session:
            if not claim(session, item, now=now, lease_s=lease_s(self.sink), overdue=overdue):
                return 0
        tries = item.attempts + 1
        self.stats.attempts += 1
        try:
            self.transport.send(item)
        except EndpointGone as exc:
            self._disable(item, exc)
            return 1
        except DeliveryFailed as exc:
            self._failed(item, tries, str(exc), exc.retry_after_s)
            return 1
        except Exception as exc:  # a rendering bug: counted as a failed try, so it ends dead, not looping
            log.exception("alerts %s: sending event %s failed unexpectedly", self.sink.name, item.event_id)
            self._failed(item, tries, f"{type(exc).__name__}: {exc}", None)
            return 1
        with self.database.write() as session:
            mark_delivered(session, item.delivery_id)
        self.stats.last_delivered_at = self.clock()
        log.info("alerts %s: delivered %s %s (node %s, try %d)", self.sink.name, item.kind, item.event_id,
                 item.node_id, tries)
        return 1

    def _failed(self, item: OutboxEvent, tries: int, error: str, retry_after_s: float | None) -> None:
        now = self.clock()
        self.stats.failures += 1
        if tries >= self.sink.max_attempts:
            retry_at = None
            log.error("alerts %s: giving up on %s %s after %d tries: %s", self.sink.name, item.kind, item.event_id,
                      tries, error)
        else:
            delay_s = retry_delay_s(
                tries,
                base_s=self.sink.backoff_base_s,
                cap_s=self.sink.backoff_cap_s,
                rng=self.rng,
                retry_after_s=retry_after_s,
                retry_after_max_s=self.sink.retry_after_max_s,
            )
            retry_at = now + timedelta(seconds=delay_s)
            self.retry_deadlines[item.delivery_id] = self.monotonic() + delay_s
            log.warning("alerts %s: try %d/%d of %s %s failed, retrying in %.1f s: %s", self.sink.name, tries,
                        self.sink.max_attempts, item.kind, item.event_id, delay_s, error)
        with self.database.write() as session:
            mark_failed(session, item.delivery_id, f"try {tries}: {error}", retry_at=retry_at)

    def _disable(self, item: OutboxEvent, exc: EndpointGone) -> None:
        reason = f"sink disabled: {exc}"
        log.error("alerts %s: receiver answered %d Gone; sink disabled until its endpoint is changed",
                  self.sink.name, exc.status_code)
        self.stats.failures += 1
        with self.database.write() as session:
            mark_failed(session, item.delivery_id, reason, retry_at=None)
            event = sink_disabled_event(
                self.alerting,
                sink_name=self.sink.name,
                endpoint_fingerprint=self.transport.endpoint_fingerprint(),
                status_code=exc.status_code,
                occurred_at=self.clock(),
            )
            add_event_once(session, event, node_id=None, now=self.clock())
            kill_pending(session, self.sink.name, reason)
        self.disabled = True

    def _endpoint_disabled(self) -> bool:
        fingerprint = self.transport.endpoint_fingerprint()
        with self.database.session() as session:
            for row in events_of_kind(session, EventKind.SINK_DISABLED):
                if row.payload.get("sink") == self.sink.name and row.payload.get("endpoint_fingerprint") == fingerprint:
                    return True
        return False

    def _kill_pending_of_disabled_sink(self) -> None:
        with self.database.write() as session:
            killed = kill_pending(session, self.sink.name, "sink disabled: its receiver answered 410 Gone")
        if killed:
            log.error("alerts %s: sink is disabled, %d deliveries marked dead", self.sink.name, killed)



def _loop(name: str, one_pass: Callable[[], float], *, stop: threading.Event, heartbeats: Beats | None,
          retry_s: float) -> None:
    """Run ``one_pass`` until ``stop``, beating the heartbeat each round; errors are logged, then retried."""
    while not stop.is_set():
        if heartbeats is not None:
            heartbeats.beat(name)
        try:
            wait_s = one_pass()
        except StorageError as exc:
            log.error("%s: storage unavailable, will retry in %.1f s: %s", name, retry_s, exc)
            wait_s = retry_s
        except Exception:  # a bug must not end alerting; logged with its traceback, then retried
            log.exception("%s: unexpected error, will retry in %.1f s", name, retry_s)
            wait_s = retry_s
        if wait_s > 0 and stop.wait(wait_s):
            break


class FleetWatcher:
    """Raises node_offline/node_online and baseline_changed events on a schedule (``alerts.outages``,
    ``alerts.baseline_watch``): facts found in the database rather than reported by a worker."""

    def __init__(
        self,
        alerting: AlertingSettings,
        database: Database,
        *,
        stop: threading.Event,
        heartbeats: Beats | None = None,
        clock: Callable[[], datetime] = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.alerting = alerting
        self.database = database
        self.stop = stop
        self.heartbeats = heartbeats
        self.clock = clock
        self.watching_since = clock()
        self.thread = threading.Thread(target=self.run, name=WATCH, daemon=True)

    @property
    def interval_s(self) -> float:
        return min(30.0, max(0.5, self.alerting.offline_after_s / 10))

    def stall_limit_s(self) -> float:
        return 3 * self.interval_s + 60.0

    def run(self) -> None:
        _loop(WATCH, self.check_once, stop=self.stop, heartbeats=self.heartbeats, retry_s=self.interval_s)

    def check_once(self) -> float:
        """Add the outage and baseline events due now; returns seconds until the next check."""
        now = self.clock()
        with self.database.write() as session:
            added = check_outages(session, self.alerting, now=now, watching_since=self.watching_since)
            added += check_baseline_changes(session, self.alerting, now=now)
        for event in added:
            log.log(log_level(event.severity), "alerts: %s", event.payload["summary"], extra={"event_kind": event.kind})
        return self.interval_s


class AlertDelivery:
    """All of alerting in the gateway: a SinkWorker per configured sink and the FleetWatcher."""

    def __init__(
        self,
        alerting: AlertingSettings,
        database: Database,
        *,
        stop: threading.Event,
        heartbeats: Beats | None = None,
        transport_factory: Callable[[AnySinkSettings, AlertingSettings, Database], SinkTransport] = make_transport,
        watch_fleet: bool = True,
    ) -> None:
        self.sink_workers = [
            SinkWorker(alerting, sink, transport_factory(sink, alerting, database), database, stop=stop, heartbeats=heartbeats)
            for sink in alerting.sinks
        ]
        self.watcher = (
            FleetWatcher(alerting, database, stop=stop, heartbeats=heartbeats) if watch_fleet else None
        )

    @property
    def threads(self) -> list[threading.Thread]:
        threads = [w.thread for w in self.sink_workers]
        return threads + ([self.watcher.thread] if self.watcher is not None else [])

    def start(self) -> None:
        for thread in self.threads:
            thread.start()

    def join(self, timeout_s: float) -> None:
        """Wait (bounded) for the threads after ``stop`` was set; an attempt in flight ends by its timeout."""
        end = time.monotonic() + timeout_s
        for thread in self.threads:
            thread.join(max(0.0, end - time.monotonic()))

    def stall_limits_s(self) -> dict[str, float]:
        limits = {w.name: w.stall_limit_s() for w in self.sink_workers}
        if self.watcher is not None:
            limits[WATCH] = self.watcher.stall_limit_s()
        return limits
