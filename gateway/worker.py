"""One node's poll loop and its cycle: acquire (node I/O) -> assess (imaging) -> decide (pure) ->
store (one transaction) -> deliver (the worker's memory, the log).

Each node has its own thread, so a node that hangs, vanishes or talks garbage never delays
the others. Everything about one measurement is stored in one transaction or not at all.
The pieces: gateway/acquisition.py (node I/O), gateway/assessment.py (imaging),
gateway/decision.py (the verdict), db/cycles.py (the transaction).
"""
from __future__ import annotations

import dataclasses
import logging
import statistics
import threading
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy.orm import Session

from alerts.alarms import BaselineSet, decommissioning_events, open_alarms
from alerts.config import AlertingSettings
from alerts.events import (
    SENSOR_FAULT_KINDS,
    log_level,
    node_decommissioned_event,
    node_misconfigured_event,
    node_recommissioned_event,
)
from alerts.sensor_faults import sensor_fault_history
from db.baselines import active_baseline, library_baseline_ids
from db.cycles import StoredCycle, store_cycle
from db.database import Database
from db.errors import DatabaseDamaged, StorageError, StorageUnavailable
from db.measurements import add_event_once
from db.models import MeasurementKind, NodeState
from db.nodes import (
    get_node,
    is_decommissioned,
    record_node_health,
    record_node_link,
    register_configured_node,
    upsert_node,
)
from db.queries import baseline_count, calibration_peaks, recent_verdicts
from db.records import CycleRecord, DiMapInput, EventInput, NodeInfo
from gateway.acquisition import (
    Acquisition,
    ClientFactory,
    Connection,
    NodeIdentityMismatch,
    SettingsChanged,
    acquire,
    open_connection,
)
from gateway.assessment import BaselineLibrary, abstained, assess_settings, gateway_map
from gateway.clock import Clock, SystemClock
from gateway.config import NodeSettings
from gateway.decision import (
    MonitoringInputs,
    NodeHistory,
    Verdict,
    comparable_inputs,
    decide_commissioning,
    decide_monitoring,
    is_commissioning,
)
from gateway.flagging import FlagState, restored_flag_state, threshold_for
from gateway.geometry import effective_geometry
from gateway.logs import node_context
from gateway.node_client import NodeClient
from gateway.node_errors import NodeClientError, NodeRebooted, NodeTimeout, ProtocolMismatch, TransferError
from gateway.watchdog import Heartbeats
from imaging.compensation import thermometer_offset_c
from imaging.detection import default_threshold
from imaging.pipeline import Assessment, assess
from nodelink.transport import PORT_ERRORS, PortVanished
from retry_timing.backoff import Backoff

log = logging.getLogger("pipesentry.gateway")
ROUTINE_STATES = frozenset({NodeState.COMMISSIONING, NodeState.CALIBRATING, NodeState.OK})  # logged at INFO

REOPEN_BACKOFF_BASE_S = 0.5  # the first retry after a failed cycle; doubling up to reopen_backoff_max_s

@dataclass
class NodeCounters:
    """Gateway-side error counts for one node (stored with the node's own counters)."""

    cycles: int = 0
    failures: int = 0  # the node did not answer as it should (of which timeouts and transfer_errors)
    timeouts: int = 0
    transfer_errors: int = 0
    port_reopens: int = 0
    storage_errors: int = 0
    internal_errors: int = 0  # bugs, logged with their traceback
    retries: int = 0  # commands and chunks sent again, over the connections closed so far

    def as_dict(self) -> dict[str, int]:
        return {f"gateway_{k}": v for k, v in self.__dict__.items() if k != "retries"}

    def count_failure(self, exc: NodeClientError) -> None:
        self.failures += 1
        if isinstance(exc, NodeTimeout):
            self.timeouts += 1
        elif isinstance(exc, TransferError | NodeRebooted):
            self.transfer_errors += 1


@dataclass
class CycleOutcome:
    measurement_id: int
    kind: MeasurementKind
    state: NodeState
    peak_di: float | None = None
    threshold: float | None = None
    axial_mm: float | None = None
    angle_deg: float | None = None


class NodeWorker:
    """Polls one node on its own schedule until ``stop`` is set."""

    def __init__(
        self,
        settings: NodeSettings,
        db: Database,
        heartbeats: Heartbeats,
        stop: threading.Event,
        *,
        backoff_max_s: float = 60.0,
        alerting: AlertingSettings | None = None,
        client_factory: ClientFactory = NodeClient,
        clock: Clock | None = None,
    ) -> None:
        self.settings = settings
        self.clock: Clock = clock or SystemClock()
        self.db = db
        self.heartbeats = heartbeats
        self.stop = stop
        # No jitter: the port is this node's alone, so there is nothing to spread.
        self.reopen_backoff = Backoff(min(REOPEN_BACKOFF_BASE_S, backoff_max_s), backoff_max_s, "none")
        self.alerting = alerting or AlertingSettings()
        self.client_factory = client_factory
        self.counters = NodeCounters()
        # (common gain, stretch, thermometer offset degC or None) the last imaged record's baseline was
        # matched with: the ring's drift, the temperature as the imaging saw it and how far the node's
        # thermometer disagrees, for the metrics thread (None until a record is imaged)
        self.last_match: tuple[float, float, float | None] | None = None
        self.conn: Connection | None = None
        self.flag: FlagState | None = None  # the flagger's memory; None: restore it from storage first
        self.library = BaselineLibrary()
        self._threshold_cache: tuple[int | None, float | None] | None = None  # (active baseline, threshold)
        self._out_of_service = False
        self._decommissioned_at: datetime | None = None  # of the decommissioning this worker saw (for node_recommissioned)
        self._connection_lock = threading.Lock()  # the metrics thread reads the open connection's retries
        self.thread = threading.Thread(target=self.run, name=f"node-{settings.id}", daemon=True)

    @property
    def name(self) -> str:
        return self.thread.name

    @property
    def out_of_service(self) -> bool:
        """Decommissioned by an admin, as this worker last noticed."""
        return self._out_of_service

    def retries_total(self) -> int:
        """Commands and chunks sent again since the worker started, over every connection."""
        with self._connection_lock:
            conn = self.conn
            return self.counters.retries + (conn.client.retried if conn is not None else 0)

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        with node_context(self.settings.id):
            self.heartbeats.beat(self.name)
            failures = 0
            monotonic = self.clock.monotonic
            next_due = monotonic()
            while not self.stop.is_set():
                wait_s = max(0.0, next_due - monotonic())
                if wait_s and self.stop.wait(wait_s):
                    break
                started = monotonic()
                try:
                    if self._decommissioned():
                        self.heartbeats.beat(self.name)  # idle by decision, not hung
                        next_due = started + self.settings.interval_s
                        continue
                    outcome = self.poll_once()
                except self._abandoned_at_shutdown() as exc:
                    log.info("stopping: the cycle in flight was abandoned, nothing of it stored (%s: %s)",
                             type(exc).__name__, exc)
                    break
                except PortVanished as exc:
                    failures += 1
                    self._drop_connection(f"port vanished: {exc}")
                except PORT_ERRORS as exc:
                    failures += 1
                    self._drop_connection(f"cannot open {self.settings.url}: {exc}")
                except ProtocolMismatch as exc:
                    failures += 1
                    self._drop_connection(f"protocol mismatch: {exc}")
                except NodeIdentityMismatch as exc:
                    failures += 1
                    self.counters.failures += 1
                    self._surface_identity(exc)
                    self._drop_connection(f"not polled: {exc}")
                except NodeClientError as exc:
                    failures += 1
                    self.counters.count_failure(exc)
                    log.warning("cycle failed: %s: %s", type(exc).__name__, exc)
                    self._record_failed_cycle()
                except StorageUnavailable as exc:
                    failures += 1
                    self.counters.storage_errors += 1
                    log.error("storage unavailable, measurement dropped, will retry: %s", exc)
                except DatabaseDamaged as exc:  # the daemon shuts down on it; nothing more is written
                    failures += 1
                    self.counters.storage_errors += 1
                    log.error("database damaged, measurement not stored: %s", exc)
                except Exception:  # a bug must not kill the node's worker; it is logged with its traceback
                    failures += 1
                    self.counters.internal_errors += 1
                    log.exception("unexpected error in the poll cycle")
                else:
                    failures = 0
                    log.info(
                        "measurement %d stored (%s): state %s, peak DI %s, threshold %s%s",
                        outcome.measurement_id,
                        outcome.kind.value,
                        outcome.state.value,
                        _fmt(outcome.peak_di),
                        _fmt(outcome.threshold),
                        ""
                        if outcome.axial_mm is None
                        else f", estimate {outcome.axial_mm:.1f} mm / {outcome.angle_deg:.1f} deg",
                        extra={"measurement_id": outcome.measurement_id, "state": outcome.state.value},
                    )
                self.heartbeats.beat(self.name)
                if failures:  # USB re-enumeration, a rebooting node: try again later and later
                    next_due = monotonic() + self.reopen_backoff.delay_s(failures)
                else:
                    next_due = max(started + self.settings.interval_s, monotonic())
            self._close()

    def _abandoned_at_shutdown(self) -> tuple[type[Exception], ...]:
        """What a cycle may fail with once ``stop`` is set: anything (the daemon closes a port stuck in a
        transfer to end it, and the read fails however it fails). Before that, nothing: the ``except``
        clause using it matches no exception, and each failure is handled by its kind below."""
        return (Exception,) if self.stop.is_set() else ()

    def _decommissioned(self) -> bool:
        """True while an admin has decommissioned this node (API): its port is released, nothing is
        polled, and the check repeats every interval so that recommissioning resumes polling.
        Each change is told to the alert sinks (node_decommissioned / node_recommissioned)."""
        with self.db.session() as session:
            decommissioned = is_decommissioned(session, self.settings.id)
        if decommissioned == self._out_of_service:
            return decommissioned
        if decommissioned:
            self._close()
        with self.db.write() as session:  # a storage error leaves the change to be noticed again next cycle
            node = get_node(session, self.settings.id)
            since = node.decommissioned_at
            decommissioned = since is not None  # as of this transaction (an admin may just have undone it)
            event: EventInput | None = None
            ends: list[EventInput] = []
            if since is not None:
                node.online = False  # a poll in flight when it was decommissioned marked it online
                # Every alarm still open about the node ends with it (told before the decommissioning).
                ends = decommissioning_events(
                    self.alerting, open_alarms(session, node.node_id), node_id=node.node_id, state=node.state.value,
                    decommissioned_at=since, by=node.decommissioned_by or "?", reason=node.decommission_reason or "",
                )
                event = node_decommissioned_event(
                    self.alerting, node_id=node.node_id, state=node.state.value,
                    decommissioned_at=since, by=node.decommissioned_by or "?",
                    reason=node.decommission_reason or "",
                )
            elif self._decommissioned_at is not None:
                event = node_recommissioned_event(
                    self.alerting, node_id=node.node_id, state=node.state.value,
                    decommissioned_at=self._decommissioned_at,
                )
            for added in [*ends, *([event] if event is not None else [])]:
                # idempotent: a restart finds the same decommissioning (and alarms), the same ids
                add_event_once(session, added, node_id=node.node_id)
        self._out_of_service, self._decommissioned_at = decommissioned, since
        if decommissioned:
            log.info("node decommissioned (API); port released, not polling until it is recommissioned")
        else:
            log.info("node recommissioned (API); polling again")
        return decommissioned

    def _drop_connection(self, why: str) -> None:
        log.warning("%s; reopening with backoff", why)
        self.counters.port_reopens += 1
        self._close()
        self._record_failed_cycle()

    def _record_failed_cycle(self) -> None:
        """A cycle that stored nothing: the node did not answer its poll as it should, so it is not
        online, and the gateway's counts of why (timeouts, transfer errors, reopens) are stored with
        the node's own counters as last read (they are otherwise stored only with a measurement)."""
        try:
            with self.db.write() as session:
                # Registered at the gateway's start; if that write failed, now (never seen until it answers).
                register_configured_node(session, self.settings.id, port_url=self.settings.url)
                node = get_node(session, self.settings.id)
                record_node_health(session, self.settings.id, online=False,
                                   error_counters={**(node.error_counters or {}), **self.counters.as_dict()})
        except StorageError as exc:
            log.error("could not record the failed cycle: %s", exc)

    def _close(self) -> None:
        with self._connection_lock:
            conn, self.conn = self.conn, None
            if conn is not None:
                self.counters.retries += conn.client.retried
        if conn is not None:
            conn.client.close()

    # ------------------------------------------------------------------ one cycle
    def connect(self) -> Connection:
        conn = open_connection(self.settings, self.client_factory)
        try:
            with self.db.write() as session:
                upsert_node(session, conn.node_info(self.settings))
                self._record_link(session, conn)
        except BaseException:
            conn.client.close()
            raise
        info = conn.info
        log.info("connected: node %s firmware %d.%d.%d, protocol %d, %d channels, boot id %#010x", info.node_id,
                 info.fw_major, info.fw_minor, info.fw_patch, info.protocol_version, info.n_channels, info.boot_id)
        return conn

    def _record_link(self, session: Session, conn: Connection, *, rebooted: bool = False) -> None:
        """What the gateway found on the port, on the node's record; a problem is also an event."""
        node = record_node_link(
            session, self.settings.id, reported_node_id=conn.info.node_id, boot_id=conn.boot_id,
            applied_settings=conn.applied(), problems=conn.problems, rebooted=rebooted,
        )
        if conn.problems:
            add_event_once(session, node_misconfigured_event(
                self.alerting, node_id=self.settings.id, state=node.state.value, problems=list(conn.problems),
                boot_id=conn.boot_id,
            ), node_id=self.settings.id)

    def _surface_identity(self, exc: NodeIdentityMismatch) -> None:
        """Another node answers on the port: registered under the configured id with the problem and an
        event, so an operator sees it; no measurement is taken or stored."""
        info = exc.info
        try:
            with self.db.write() as session:
                upsert_node(session, NodeInfo(
                    node_id=self.settings.id, port_url=self.settings.url, firmware=info.firmware_version,
                    protocol_version=info.protocol_version, n_channels=info.n_channels, fs_hz=info.fs_hz,
                    geometry=effective_geometry(info, self.settings.geometry).geometry,
                ))
                node = record_node_link(session, self.settings.id, reported_node_id=info.node_id,
                                        boot_id=info.boot_id, applied_settings=None, problems=[exc.problem])
                add_event_once(session, node_misconfigured_event(
                    self.alerting, node_id=self.settings.id, state=node.state.value, problems=[exc.problem],
                    boot_id=info.boot_id,
                ), node_id=self.settings.id)
        except StorageError as storage:
            log.error("could not record the identity mismatch: %s", storage)

    def poll_once(self) -> CycleOutcome:
        """One cycle: acquire (node I/O) -> assess (imaging) -> decide (pure) -> store (one transaction) -> deliver."""
        if self.conn is None:
            self.conn = self.connect()
        conn = self.conn
        self.counters.cycles += 1
        with self.db.session() as session:
            history = node_history(session, self.settings.id)
        if is_commissioning(self.settings, history):
            acquisition = self._acquire(conn, commissioning=True, read_node_map=False)
            if acquisition.connection.stale:
                raise SettingsChanged(f"commissioning measurement {acquisition.reply.measurement_id} was taken with "
                                      f"other settings than configured ({', '.join(acquisition.unexpected)}): not a "
                                      "baseline, dropped")
            verdict = decide_commissioning(self.settings, history)
            maps: list[DiMapInput] = []
        else:
            with self.db.session() as session:
                inputs = self._monitoring_inputs(session, history, conn)
            acquisition = self._acquire(conn, commissioning=False, read_node_map=self.settings.read_node_di)
            imaging = assess_settings(self.settings, inputs.threshold, conn.view.wall_mm)
            inputs, mismatch = comparable_inputs(inputs, self.library.settings(list(inputs.library_ids)),
                                                 acquisition.settings)
            if mismatch is not None:
                assessment = abstained(imaging, mismatch)
            else:
                assessment = assess(acquisition.measurement, list(inputs.library), imaging)
            if assessment.baseline is not None:
                self.last_match = (assessment.baseline.gain, assessment.baseline.stretch,
                                   thermometer_offset_c(assessment.baseline, acquisition.temperature_c))
            _log_assessment(assessment)
            verdict = decide_monitoring(
                self.settings, history, inputs, assessment, temperature_c=acquisition.temperature_c, now=self.clock.wall()
            )
            own_map = gateway_map(assessment, list(inputs.library_ids))
            maps = [m for m in (own_map, acquisition.node_map) if m is not None]
        record = CycleRecord(
            acquisition=acquisition.record(),
            kind=verdict.kind,
            error_counters={**acquisition.link_counters, **self.counters.as_dict()},
            di_maps=maps,
            detection=verdict.detection,
            state_change=verdict.state_change,
            activate_baseline=verdict.activate_baseline,
        )
        with self.db.write() as session:
            stored = store_cycle(
                session, self.settings.id, record,
                lambda measurement_id: verdict.events(self.alerting, node_id=self.settings.id,
                                                      measurement_id=measurement_id),
            )
        if acquisition.filled_slot and self.conn is not None:  # the node's own maps are made against this record
            self.conn = dataclasses.replace(self.conn, slot_measurement_id=stored.measurement_id)
        return self._deliver(verdict, stored, acquisition)

    def _acquire(self, conn: Connection, *, commissioning: bool, read_node_map: bool) -> Acquisition:
        """The node I/O of the cycle; a connection renewed on the way (a reboot) is kept and recorded."""
        acquisition = acquire(conn, self.settings, commissioning=commissioning, read_node_map=read_node_map,
                              now=self.clock.wall)
        renewed = acquisition.connection
        self.conn = renewed
        if renewed.info is not conn.info:
            with self.db.write() as session:
                self._record_link(session, renewed, rebooted=acquisition.rebooted_from is not None)
        return acquisition

    def _monitoring_inputs(self, session: Session, history: NodeHistory, conn: Connection) -> MonitoringInputs:
        """The baseline library, the threshold, the flagger's memory and the recent sensor verdicts."""
        node_id = self.settings.id
        library_ids = library_baseline_ids(session, node_id, self.settings.imaging.library_size)
        if self.flag is None:  # the first monitor cycle since the worker started: restore the hysteresis
            readings = recent_verdicts(session, node_id, limit=self.settings.threshold.hysteresis_count)
            self.flag = restored_flag_state(readings, history.state)
        return MonitoringInputs(
            flag=self.flag,
            threshold=self._threshold(session, history),
            library_ids=library_ids,
            library=self.library.load(session, library_ids, conn.view),
            sensor_faults=sensor_fault_history(session, node_id, self.alerting.sensor_fault_count),
            alarms=open_alarms(session, node_id),
        )

    def _threshold(self, session: Session, history: NodeHistory) -> float | None:
        """The node's threshold: absolute, or calibrated on the first K monitor peaks since its baseline.

        A calibrated value is kept for as long as the active baseline stays the same.
        """
        cache = self._threshold_cache
        if cache is not None and cache[0] == history.active_baseline_id and cache[1] is not None:
            return cache[1]
        settings = self.settings.threshold
        peaks: list[float] = []
        if settings.mode == "calibrated" and history.active_baseline_id is not None:
            peaks = calibration_peaks(
                session, self.settings.id, after_measurement_id=history.active_baseline_id,
                limit=settings.calibration_count,
            )
        floor = settings.floor
        if floor is None:
            floor = default_threshold(self.settings.imaging.method, self.settings.imaging.feature)
        value = threshold_for(settings, peaks, floor)
        if value is not None and settings.mode == "calibrated":
            log.info("threshold calibrated: %.4g from %d baseline-condition peak DIs (median %.4g, floor %.4g)",
                     value, len(peaks), statistics.median(peaks), floor)
        self._threshold_cache = (history.active_baseline_id, value)
        return value

    def _deliver(self, verdict: Verdict, stored: StoredCycle, acquisition: Acquisition) -> CycleOutcome:
        """After the commit: the worker's memory follows the verdict, the log tells what happened.
        (The alert sinks are sent the outbox by alerts/delivery.py.)"""
        self.flag = verdict.flag
        if verdict.joins_library:
            log.info("measurement %d joins the baseline library at %.2f degC", stored.measurement_id,
                     acquisition.temperature_c)
        for event in stored.events:
            if event.kind in SENSOR_FAULT_KINDS:
                log.log(log_level(event.severity), "%s: %s", event.kind, event.payload["summary"])
        change = verdict.state_change
        if change is not None:
            # Commissioning -> calibrating -> ok is routine; a flag or a blind node is not.
            level = logging.INFO if change.to_state in ROUTINE_STATES else logging.WARNING
            log.log(level, "state %s -> %s", change.from_state.value, change.to_state.value,
                    extra={"from_state": change.from_state.value, "to_state": change.to_state.value})
        detection = verdict.detection
        return CycleOutcome(
            stored.measurement_id,
            verdict.kind,
            verdict.state,
            peak_di=None if detection is None else detection.peak_di,
            threshold=None if detection is None else detection.threshold,
            axial_mm=None if detection is None else detection.axial_mm,
            angle_deg=None if detection is None else detection.angle_deg,
        )


def node_history(session: Session, node_id: str) -> NodeHistory:
    """What storage says about the node before a cycle (the node is registered by ``connect``)."""
    baseline = active_baseline(session, node_id)
    return NodeHistory(
        state=get_node(session, node_id).state,
        active_baseline_id=None if baseline is None else baseline.measurement_id,
        baseline_set_at=None if baseline is None else baseline.created_at,
        n_baselines=baseline_count(session, node_id),
        baseline=None if baseline is None else BaselineSet(
            baseline_id=baseline.id, set_at=baseline.created_at, by=baseline.created_by, reason=baseline.reason),
    )


def _log_assessment(assessment: Assessment) -> None:
    if assessment.no_valid_baseline is not None:
        log.warning("no map: %s", assessment.no_valid_baseline.reason)
    if assessment.strong_change is not None:
        change = assessment.strong_change
        how = ("" if change.refused_stretch is None else
               f" as recorded (the stretch search wanted {change.refused_stretch:+.2%}, beyond the range)")
        if change.searched_stretch is not None and assessment.baseline is not None:
            how += (f" warmed as the thermometers say ({assessment.baseline.stretch:+.3%}; the stretch search "
                    f"wanted {change.searched_stretch:+.3%})")
        log.warning("strong change: the baseline%s leaves %.3g of the record unexplained (limit %.3g), the defects "
                    "located explain %.0f%% of it: reported as defects", how, change.residual,
                    change.max_residual, 100 * change.explained)
    for fault in assessment.sensor_faults:
        log.warning("sensor fault on receiver %d (%.1f deg): %s; left out of the map",
                    fault.rx_index, fault.rx_angle_deg, fault.kind)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"
