"""One node's poll loop: STATUS, ACQUIRE, READ_TRACES, READ_DI, recompute, flag, store.

Each node has its own thread, so a node that hangs, vanishes or talks garbage never delays
the others. Everything about one measurement is stored in one transaction or not at all.
"""
from __future__ import annotations

import logging
import math
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from sqlalchemy import func, select

from alerts.config import AlertingSettings
from alerts.events import node_decommissioned_event, node_recommissioned_event, state_change_event
from alerts.outbox import add_event_once
from alerts.sensor_faults import check_sensor_faults
from db.baselines import active_baseline, set_active_baseline
from db.clock import utc_now
from db.database import Database
from db.errors import StorageError, StorageUnavailable
from db.measurements import add_event, store_measurement
from db.models import DetectionRow, MapSource, MeasurementKind, MeasurementRow, NodeState
from db.nodes import get_node, is_decommissioned, record_node_health, upsert_node
from db.records import DiMapInput, MapGrid, NodeInfo, StateChangeInput
from gateway.assessment import BaselineLibrary, assess_settings, detection_input, joins_library, run_assessment
from gateway.config import NodeSettings
from gateway.flagging import FLAGGING_STATES, FlagState, step, threshold_for
from gateway.logs import node_context
from gateway.measurement_build import NodeGeometryView, effective_geometry, measurement_from_codes
from gateway.node_client import (
    NodeClient,
    NodeClientError,
    PortVanished,
    ProtocolMismatch,
)
from gateway.transport import PORT_ERRORS
from gateway.watchdog import Heartbeats
from imaging.detection import default_threshold
from protocol.messages import ConfigureReply, InfoReply

log = logging.getLogger("pipesentry.gateway")

@dataclass
class Connection:
    """What the gateway knows about a node while its port is open."""

    client: NodeClient
    info: InfoReply
    config: ConfigureReply
    view: NodeGeometryView


@dataclass
class NodeCounters:
    """Gateway-side error counts for one node (stored with the node's own counters)."""

    cycles: int = 0
    failures: int = 0
    timeouts: int = 0
    transfer_errors: int = 0
    port_reopens: int = 0
    storage_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f"gateway_{k}": v for k, v in self.__dict__.items()}


@dataclass
class CycleOutcome:
    measurement_id: int
    kind: MeasurementKind
    state: NodeState
    peak_di: float | None = None
    threshold: float | None = None
    axial_mm: float | None = None
    angle_deg: float | None = None
    extra: dict = field(default_factory=dict)


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
        client_factory: Callable[..., NodeClient] = NodeClient,
    ) -> None:
        self.settings = settings
        self.db = db
        self.heartbeats = heartbeats
        self.stop = stop
        self.backoff_max_s = backoff_max_s
        self.alerting = alerting or AlertingSettings()
        self.client_factory = client_factory
        self.counters = NodeCounters()
        self.conn: Connection | None = None
        self.flag = FlagState()
        self.library = BaselineLibrary(settings.imaging.library_size)
        self._threshold_cache: tuple[int, float | None] | None = None
        self._flag_loaded = False
        self._n_baselines = 0
        self._out_of_service = False
        self._decommissioned_at = None  # of the decommissioning this worker saw (for node_recommissioned)
        self.thread = threading.Thread(target=self.run, name=f"node-{settings.id}", daemon=True)

    @property
    def name(self) -> str:
        return self.thread.name

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        with node_context(self.settings.id):
            self.heartbeats.beat(self.name)
            failures = 0
            next_due = time.monotonic()
            while not self.stop.is_set():
                wait_s = max(0.0, next_due - time.monotonic())
                if wait_s and self.stop.wait(wait_s):
                    break
                started = time.monotonic()
                try:
                    if self._decommissioned():
                        self.heartbeats.beat(self.name)  # idle by decision, not hung
                        next_due = started + self.settings.interval_s
                        continue
                    outcome = self.poll_once()
                except PortVanished as exc:
                    failures += 1
                    self._drop_connection(f"port vanished: {exc}")
                except PORT_ERRORS as exc:
                    failures += 1
                    self._drop_connection(f"cannot open {self.settings.url}: {exc}")
                except ProtocolMismatch as exc:
                    failures += 1
                    self._drop_connection(f"protocol mismatch: {exc}")
                except NodeClientError as exc:
                    failures += 1
                    self.counters.failures += 1
                    log.warning("cycle failed: %s: %s", type(exc).__name__, exc)
                except StorageUnavailable as exc:
                    failures += 1
                    self.counters.storage_errors += 1
                    log.error("storage unavailable, measurement dropped, will retry: %s", exc)
                except Exception:  # a bug must not kill the node's worker; it is logged with its traceback
                    failures += 1
                    self.counters.failures += 1
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
                if failures:
                    # Exponential backoff (USB re-enumeration, a rebooting node), capped.
                    next_due = time.monotonic() + min(self.backoff_max_s, 0.5 * 2 ** min(failures - 1, 16))
                else:
                    next_due = max(started + self.settings.interval_s, time.monotonic())
            self._close()

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
            if decommissioned:
                node.online = False  # a poll in flight when it was decommissioned marked it online
                event = node_decommissioned_event(
                    self.alerting, node_id=node.node_id, state=node.state.value,
                    decommissioned_at=node.decommissioned_at, by=node.decommissioned_by or "?",
                    reason=node.decommission_reason or "",
                )
            elif self._decommissioned_at is not None:
                event = node_recommissioned_event(
                    self.alerting, node_id=node.node_id, state=node.state.value,
                    decommissioned_at=self._decommissioned_at,
                )
            else:
                event = None
            if event is not None:  # idempotent: a restart finds the same decommissioning, the same id
                add_event_once(session, event, node_id=node.node_id)
        self._out_of_service, self._decommissioned_at = decommissioned, since
        if decommissioned:
            log.warning("node decommissioned (API); port released, not polling until it is recommissioned")
        else:
            log.info("node recommissioned (API); polling again")
        return decommissioned

    def _drop_connection(self, why: str) -> None:
        log.warning("%s; reopening with backoff", why)
        self.counters.port_reopens += 1
        self._close()
        try:
            with self.db.write() as session:
                record_node_health(session, self.settings.id, online=False)
        except (StorageError, LookupError):
            pass  # the node may not be known yet (never answered), or storage is down: nothing to mark

    def _close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.client.close()
            finally:
                self.conn = None

    # ------------------------------------------------------------------ one cycle
    def connect(self) -> Connection:
        s = self.settings
        client = self.client_factory(s.url, baudrate=s.baud, timeout_s=s.timeout_s, retries=s.retries)
        try:
            info = client.info()
            config = client.configure(s.excitation_hz, s.cycles, s.averaging, min(s.n_samples, info.max_samples))
        except BaseException:
            client.close()
            raise
        if info.node_id != s.id:
            log.warning("port %s answers as node %r, configured as %r", s.url, info.node_id, s.id)
        view = effective_geometry(info, s.geometry)
        with self.db.write() as session:
            upsert_node(
                session,
                NodeInfo(
                    node_id=s.id,
                    port_url=s.url,
                    firmware=f"{info.fw_major}.{info.fw_minor}.{info.fw_patch}",
                    protocol_version=info.protocol_version,
                    n_channels=info.n_channels,
                    fs_hz=info.fs_hz,
                    geometry=view.geometry,
                ),
            )
        log.info("connected: node %s firmware %d.%d.%d, %d channels", info.node_id, info.fw_major, info.fw_minor,
                 info.fw_patch, info.n_channels)
        return Connection(client, info, config, view)

    def poll_once(self) -> CycleOutcome:
        if self.conn is None:
            self.conn = self.connect()
        conn = self.conn
        self.counters.cycles += 1
        status = conn.client.status()
        with self.db.session() as session:
            baseline_row = active_baseline(session, self.settings.id)
            n_baselines = session.scalar(
                select(func.count()).where(
                    MeasurementRow.node_id == self.settings.id, MeasurementRow.kind == MeasurementKind.BASELINE
                )
            )
        commissioning = baseline_row is None or n_baselines < self.settings.commissioning_count
        self._n_baselines = n_baselines
        acq = conn.client.acquire(baseline=commissioning)
        transfer = conn.client.read_traces(acq.measurement_id)
        current = measurement_from_codes(
            transfer.codes,
            transfer.volts_per_code,
            fs_hz=transfer.fs_hz,
            t0_s=transfer.t0_s,
            view=conn.view,
            channels=transfer.channels,
            excitation_hz=conn.config.excitation_hz,
            cycles=conn.config.cycles,
            temperature_c=transfer.temperature_c,
        )
        node_errors = {
            "node_crc_errors": status.crc_errors,
            "node_framing_errors": status.framing_errors,
            "node_rejected_requests": status.rejected_requests,
            "client_frame_errors": conn.client.frame_errors,
            "client_retries": conn.client.retried,
            **self.counters.as_dict(),
        }
        if commissioning:
            return self._store_baseline(acq, transfer, current, baseline_row is None, node_errors)
        return self._store_monitor(conn, status, acq, transfer, current, baseline_row.measurement_id, node_errors)

    def _acquisition_fields(self, acq, transfer, current) -> dict:
        """What store_measurement needs to know about the acquisition itself."""
        return dict(
            acquired_at=utc_now(),
            node_measurement_id=acq.measurement_id,
            codes=transfer.codes,
            volts_per_code=transfer.volts_per_code,
            fs_hz=transfer.fs_hz,
            t0_s=transfer.t0_s,
            averaging=self.conn.config.averaging,
            excitation_hz=current.excitation_hz,
            cycles=current.cycles,
            temperature_c=_finite_or_none(transfer.temperature_c),
        )

    def _store_baseline(self, acq, transfer, current, activate: bool, node_errors) -> CycleOutcome:
        """A commissioning measurement: stored as a baseline; the first one becomes the active baseline."""
        done = self._n_baselines + 1 >= self.settings.commissioning_count
        after = NodeState.CALIBRATING if self.settings.threshold.mode == "calibrated" else NodeState.OK
        with self.db.write() as session:
            prev_state = get_node(session, self.settings.id).state
            new_state = after if done else NodeState.COMMISSIONING
            row = store_measurement(
                session,
                self.settings.id,
                kind=MeasurementKind.BASELINE,
                **self._acquisition_fields(acq, transfer, current),
                state_change=StateChangeInput(prev_state, new_state) if new_state != prev_state else None,
            )
            if activate:
                set_active_baseline(
                    session, self.settings.id, row.id, created_by="gateway", reason="commissioning: first measurement"
                )
            record_node_health(session, self.settings.id, online=True, error_counters=node_errors)
            measurement_id = row.id
        self.flag = FlagState()
        return CycleOutcome(measurement_id, MeasurementKind.BASELINE, new_state)

    def _threshold(self, session, baseline_measurement_id: int) -> float | None:
        """The node's threshold: absolute, or calibrated on the first K monitor peaks since its baseline."""
        cache = self._threshold_cache
        if cache is not None and cache[0] == baseline_measurement_id and cache[1] is not None:
            return cache[1]
        settings = self.settings.threshold
        peaks: list[float] = []
        if settings.mode == "calibrated":
            since = active_baseline(session, self.settings.id)
            rows = session.scalars(
                select(DetectionRow.peak_di)
                .where(
                    DetectionRow.node_id == self.settings.id,
                    DetectionRow.created_at >= since.created_at,
                    DetectionRow.threshold.is_(None),
                    DetectionRow.peak_di.is_not(None),
                )
                .order_by(DetectionRow.id)
                .limit(settings.calibration_count)
            ).all()
            peaks = [float(p) for p in rows]
        floor = settings.floor
        if floor is None:
            floor = default_threshold(self.settings.imaging.method, self.settings.imaging.feature)
        value = threshold_for(settings, peaks, floor)
        if value is not None and settings.mode == "calibrated":
            log.info("threshold calibrated: %.4g from %d baseline-condition peak DIs (median %.4g, floor %.4g)",
                     value, len(peaks), statistics.median(peaks), floor)
        self._threshold_cache = (baseline_measurement_id, value)
        return value

    def _load_flag_state(self, session, node_state: NodeState) -> None:
        """Rebuild the hysteresis counters from the last detections after a restart."""
        m = self.settings.threshold.hysteresis_count
        rows = session.execute(
            select(DetectionRow.peak_di, DetectionRow.threshold)
            .where(
                DetectionRow.node_id == self.settings.id,
                DetectionRow.threshold.is_not(None),
                DetectionRow.peak_di.is_not(None),
            )
            .order_by(DetectionRow.id.desc())
            .limit(m)
        ).all()
        above = below = 0
        for peak, thr in rows:
            if peak > thr and below == 0:
                above += 1
            elif peak <= thr and above == 0:
                below += 1
            else:
                break
        state = node_state if node_state in FLAGGING_STATES else NodeState.OK
        self.flag = FlagState(state, above=above, below=below if state == NodeState.DAMAGE else 0)
        self._flag_loaded = True

    def _store_monitor(self, conn, status, acq, transfer, current, baseline_id: int, node_errors) -> CycleOutcome:
        with self.db.session() as session:
            library_ids = self.library.ids(session, self.settings.id)
            library = self.library.load(session, library_ids, conn.view)
            threshold = self._threshold(session, baseline_id)
            baseline_set_at = active_baseline(session, self.settings.id).created_at
        result = run_assessment(current, library, assess_settings(self.settings, threshold, conn.view.wall_mm))
        maps = []
        if result.di_map is not None:
            maps.append(
                DiMapInput(
                    source=MapSource.GATEWAY,
                    method=result.method,
                    grid=MapGrid(**result.di_map.grid.spec()),
                    pixels=result.di_map.pixels.astype(np.float32),
                    baseline_measurement_id=library_ids[result.baseline.index],
                )
            )
        if self.settings.read_node_di and status.baseline_stored:
            try:
                computed = conn.client.compute_di(acq.measurement_id)
                node_map = conn.client.read_di(computed.di_id)
                maps.append(
                    DiMapInput(
                        source=MapSource.NODE,
                        method=f"paper-decimated-{node_map.decimation}",
                        grid=MapGrid(**node_map.grid.spec()),
                        pixels=node_map.pixels.astype(np.float32),
                        baseline_measurement_id=None,
                    )
                )
            except NodeClientError as exc:
                # The gateway's own map is what flags damage; the node's map is for comparison.
                log.warning("node DI map not read this cycle: %s: %s", type(exc).__name__, exc)
        if result.no_valid_baseline is not None:
            log.warning("no map: %s", result.no_valid_baseline.reason)
        for fault in result.sensor_faults:
            log.warning("sensor fault on receiver %d (%.1f deg): %s; left out of the map",
                        fault.rx_index, fault.rx_angle_deg, fault.kind)
        with self.db.write() as session:
            node = get_node(session, self.settings.id)
            if not self._flag_loaded:
                self._load_flag_state(session, node.state)
            prev_state = node.state
            if not result.valid_baseline:
                new_flag = step(self.flag, None, math.inf, self.settings.threshold.hysteresis_count)
            elif threshold is None:
                new_flag = FlagState(NodeState.CALIBRATING)
            else:
                new_flag = step(self.flag, result.peak_di, threshold, self.settings.threshold.hysteresis_count)
            new_state = new_flag.state
            change = StateChangeInput(prev_state, new_state) if new_state != prev_state else None
            detection = detection_input(result, new_state, threshold, library_ids)
            joins = joins_library(
                self.settings,
                state=new_state,
                peak_di=detection.peak_di,
                threshold=threshold,
                temperature_c=_finite_or_none(transfer.temperature_c),
                library=library,
                baseline_age_days=(utc_now() - baseline_set_at).total_seconds() / 86400.0,
            )
            row = store_measurement(
                session,
                self.settings.id,
                kind=MeasurementKind.BASELINE if joins else MeasurementKind.MONITOR,
                **self._acquisition_fields(acq, transfer, current),
                di_maps=maps,
                detection=detection,
                state_change=change,
            )
            if change is not None:
                # In the same transaction as the state change it reports (the outbox).
                event = state_change_event(
                    self.alerting,
                    node_id=self.settings.id,
                    from_state=change.from_state.value,
                    to_state=change.to_state.value,
                    measurement_id=row.id,
                    peak_di=detection.peak_di,
                    threshold=threshold,
                    axial_mm=detection.axial_mm,
                    angle_deg=detection.angle_deg,
                    reason=detection.abstain_reason,
                )
                if event is not None:
                    add_event(session, event, node_id=self.settings.id)
            # Receivers turned faulty or healthy again: in the same transaction as the detection.
            fault_events = check_sensor_faults(session, self.alerting, node_id=self.settings.id, measurement_id=row.id,
                                               faults=detection.sensor_faults, state=new_state.value)
            record_node_health(session, self.settings.id, online=True, error_counters=node_errors)
            measurement_id = row.id
        self.flag = new_flag
        if joins:
            log.info("measurement %d joins the baseline library at %.2f degC (%d baselines)",
                     measurement_id, transfer.temperature_c, len(library) + 1)
        for event in fault_events:
            log.warning("%s: %s", event.kind, event.payload["summary"])
        if change is not None:
            log.warning("state %s -> %s", change.from_state.value, change.to_state.value,
                        extra={"from_state": change.from_state.value, "to_state": change.to_state.value})
        return CycleOutcome(
            measurement_id,
            MeasurementKind.MONITOR,
            new_state,
            peak_di=detection.peak_di,
            threshold=threshold,
            axial_mm=detection.axial_mm,
            angle_deg=detection.angle_deg,
        )


def _finite_or_none(value: float) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"
