"""Acquisition, the node I/O of a cycle: open and configure a node, then STATUS, ACQUIRE, READ_TRACES
and (for a monitor measurement) the node's own map, COMPUTE_DI / READ_DI.

No database and no decisions here: what comes back is typed values that the cycle assesses,
decides on and stores (gateway/worker.py). The node is checked here: its identity (INFO's
node_id), the settings it applied (CONFIGURE_REPLY against the request), its reboots (a new
boot_id in STATUS: INFO and CONFIGURE again before the next record) and the settings each
record was taken with (docs/protocol.md section 3.3), which are what is stored.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from db.clock import utc_now
from db.measurement_build import NodeGeometryView, measurement_from_codes
from db.models import MapSource
from db.records import AcquisitionInput, DiMapInput, MapGrid, NodeInfo
from gateway.config import NodeSettings
from gateway.geometry import effective_geometry
from gateway.node_client import NodeClient
from gateway.node_errors import NodeClientError, NodeRebooted, ProtocolMismatch
from gateway.node_transfers import TraceTransfer, channels_of
from gateway.record_settings import (
    RecordSettings,
    SettingsNotStated,
    applied_settings,
    configure_problems,
    differences,
    stated_settings,
)
from imaging.measurement import Measurement
from protocol.messages import (
    CAP_BASELINE_SLOT,
    CAP_ON_BOARD_DI,
    AcquireReply,
    ConfigureReply,
    ConfigureRequest,
    InfoReply,
    StatusReply,
)

log = logging.getLogger("pipesentry.gateway")

ClientFactory = Callable[..., NodeClient]


class NodeIdentityMismatch(NodeClientError):
    """The port answers as another node than the one configured on it (a swapped cable, a wrong
    config): nothing is acquired or stored under the configured identity."""

    def __init__(self, info: InfoReply, settings: NodeSettings) -> None:
        super().__init__(f"port {settings.url} answers as node {info.node_id!r}, configured as {settings.id!r}")
        self.info = info
        self.problem = f"node_id: the node on {settings.url} reports {info.node_id!r}, configured {settings.id!r}"


class SettingsChanged(NodeClientError):
    """A record was taken with other settings than the node applied at the last CONFIGURE (it
    rebooted unseen): a version-1 record cannot say what they were, and no such record becomes a
    baseline. The node is configured again before the next record."""


@dataclass(frozen=True)
class Connection:
    """What the gateway knows about a node while its port is open (for one boot of the node)."""

    client: NodeClient
    info: InfoReply
    config: ConfigureReply  # the settings the node says it applied
    view: NodeGeometryView
    asked: ConfigureRequest | None = None  # what the gateway sent
    problems: tuple[str, ...] = ()  # how the node differs from its configuration (surfaced, not fatal)
    slot_measurement_id: int | None = None  # the stored record in the node's baseline slot, this boot
    stale: bool = False  # settings to send again before the next record

    @property
    def boot_id(self) -> int:
        return self.info.boot_id

    def node_info(self, settings: NodeSettings) -> NodeInfo:
        """The node's identity and configuration, as storage registers it."""
        info = self.info
        return NodeInfo(
            node_id=settings.id,
            port_url=settings.url,
            firmware=f"{info.fw_major}.{info.fw_minor}.{info.fw_patch}",
            protocol_version=info.protocol_version,
            n_channels=info.n_channels,
            fs_hz=info.fs_hz,
            geometry=self.view.geometry,
        )

    def applied(self) -> dict[str, float | int]:
        """The settings in force on the node, as the API shows them."""
        c = self.config
        return {"excitation_hz": c.excitation_hz, "cycles": c.cycles, "averaging": c.averaging,
                "channel_mask": c.channel_mask, "n_samples": c.n_samples}


def requested_configuration(settings: NodeSettings, info: InfoReply) -> tuple[ConfigureRequest, list[str]]:
    """The CONFIGURE the gateway sends (all channels), and the problem when the node cannot take
    the configured record length (its INFO ``max_samples``)."""
    problems = []
    n_samples = settings.n_samples
    if n_samples > info.max_samples:
        problems.append(f"n_samples: {n_samples} configured, the node takes at most {info.max_samples}; "
                        f"records are {info.max_samples} long")
        n_samples = info.max_samples
    mask = (1 << info.n_channels) - 1
    return ConfigureRequest(settings.excitation_hz, settings.cycles, settings.averaging, mask, n_samples), problems


def _configured(client: NodeClient, info: InfoReply, settings: NodeSettings) -> Connection:
    if info.node_id != settings.id:
        raise NodeIdentityMismatch(info, settings)
    asked, problems = requested_configuration(settings, info)
    applied = client.configure(asked.excitation_hz, asked.cycles, asked.averaging, asked.n_samples)
    problems += configure_problems(asked, applied)
    for problem in problems:
        log.warning("settings not as configured: %s", problem)
    return Connection(client, info, applied, effective_geometry(info, settings.geometry), asked, tuple(problems))


def open_connection(settings: NodeSettings, client_factory: ClientFactory = NodeClient) -> Connection:
    """Open the node's port, ask INFO, check its identity and CONFIGURE it; the port is closed
    again if any of it fails."""
    client = client_factory(settings.url, **settings.client_options())
    try:
        return _configured(client, client.info(), settings)
    except BaseException:
        client.close()
        raise


def renewed(conn: Connection, settings: NodeSettings) -> Connection:
    """INFO and CONFIGURE again on the open port (after a reboot, or a record with other settings)."""
    return _configured(conn.client, conn.client.info(), settings)


@dataclass(frozen=True)
class Acquisition:
    """One measurement as the node delivered it, in codes and in volts, and what the link counted."""

    acquired_at: datetime
    status: StatusReply  # the node's STATUS before it acquired
    reply: AcquireReply
    transfer: TraceTransfer
    settings: RecordSettings  # what the node says the record was taken with
    measurement: Measurement  # the traces in volts with the geometry the gateway images with
    node_map: DiMapInput | None  # the node's on-board DI map, when asked for and read
    link_counters: dict[str, int]  # the node's and the client's error counts after this acquisition
    connection: Connection  # the connection after it (renewed after a reboot)
    rebooted_from: int | None = None  # the boot id before the reboot noticed this cycle
    filled_slot: bool = False  # the record is now in the node's baseline slot
    unexpected: tuple[str, ...] = ()  # how the record's settings differ from what the node applied

    @property
    def averaging(self) -> int:
        return self.settings.averaging

    @property
    def temperature_c(self) -> float | None:
        value = self.transfer.temperature_c
        return value if value is not None and math.isfinite(value) else None

    def record(self) -> AcquisitionInput:
        """What storage keeps of it: the settings as the node stated them."""
        t, s = self.transfer, self.settings
        return AcquisitionInput(
            acquired_at=self.acquired_at,
            node_measurement_id=self.reply.measurement_id,
            codes=t.codes,
            volts_per_code=t.volts_per_code,
            fs_hz=s.fs_hz,
            t0_s=s.t0_s,
            averaging=s.averaging,
            excitation_hz=s.excitation_hz,
            cycles=s.cycles,
            temperature_c=self.temperature_c,
            velocity_m_s=self.measurement.velocity_m_s,
            wall_mm=self.measurement.wall_mm,
            boot_id=self.reply.boot_id,
        )


def _record_settings(conn: Connection, reply: AcquireReply, transfer: TraceTransfer) -> RecordSettings:
    """What the record was taken with: stated by a version-2 node (ACQUIRE_REPLY and TRACE_META must
    agree); for a version-1 node, what it applied at CONFIGURE, valid only within that boot."""
    n_channels, n_samples = transfer.codes.shape
    if conn.client.version is not None and conn.client.version >= 2:
        try:
            settings = stated_settings(reply, n_channels=n_channels, n_samples=n_samples, t0_s=transfer.t0_s)
        except SettingsNotStated as exc:
            raise ProtocolMismatch(str(exc)) from exc
        meta = (transfer.excitation_hz, transfer.cycles, transfer.averaging, transfer.record_n_samples)
        said = (reply.excitation_hz, reply.cycles, reply.averaging, reply.n_samples)
        if meta != said or transfer.record_channels != channels_of(reply.channel_mask):
            raise ProtocolMismatch(f"TRACE_META of measurement {reply.measurement_id} states {meta}, "
                                   f"its ACQUIRE_REPLY {said}")
        return settings
    if reply.boot_id != conn.boot_id:
        raise SettingsChanged(f"the node rebooted before measurement {reply.measurement_id} (boot id "
                              f"{conn.boot_id:#010x} -> {reply.boot_id:#010x}); a version-1 record does not say "
                              "what it was taken with: dropped, the node is configured again")
    return applied_settings(conn.config, fs_hz=transfer.fs_hz, t0_s=transfer.t0_s)


def acquire(
    conn: Connection, settings: NodeSettings, *, commissioning: bool, read_node_map: bool,
    now: Callable[[], datetime] = utc_now,
) -> Acquisition:
    """STATUS, ACQUIRE and READ_TRACES; with ``read_node_map`` also the node's own map of it.

    ``acquired_at`` is ``now()`` as the ACQUIRE is sent: when the node records (it acquires on
    receipt), whatever the reply, a retry or the transfer afterwards take.

    A new boot id in STATUS (or settings left stale by the last record) means INFO and CONFIGURE
    again first. A commissioning record fills the node's baseline slot; so does the first record
    after a reboot or a (re)connection, so that the node's own maps go on (against that record).
    The node's map is for comparison only (the gateway's own map flags damage), so failing to
    read it is logged and the acquisition goes on without it.
    """
    client = conn.client
    status = client.status()
    rebooted_from = None
    if status.boot_id != conn.boot_id or conn.stale:
        if status.boot_id != conn.boot_id:
            rebooted_from = conn.boot_id
            log.warning("node rebooted (boot id %#010x -> %#010x): INFO and CONFIGURE again", conn.boot_id,
                        status.boot_id)
        conn = renewed(conn, settings)
    info = conn.info
    has_slot = info.has(CAP_BASELINE_SLOT)
    node_maps = read_node_map and info.has(CAP_ON_BOARD_DI) and has_slot
    fill_slot = has_slot and (commissioning or (node_maps and (status.baseline_id == 0
                                                               or conn.slot_measurement_id is None)))
    acquired_at = now()
    reply = client.acquire(baseline=fill_slot)
    channels = list(channels_of(reply.channel_mask))  # the record's, whatever was configured
    transfer = client.read_traces(reply.measurement_id, channels=channels)
    if transfer.boot_id != reply.boot_id:
        raise NodeRebooted(f"boot id {reply.boot_id:#010x} at ACQUIRE, {transfer.boot_id:#010x} at READ_TRACES")
    record = _record_settings(conn, reply, transfer)
    expected = applied_settings(conn.config, fs_hz=transfer.fs_hz, t0_s=transfer.t0_s)
    unexpected = tuple(differences(record, expected, "applied"))
    if reply.boot_id != conn.boot_id or unexpected:
        log.warning("measurement %d taken with other settings than configured (%s; boot id %#010x): configuring "
                    "the node again", reply.measurement_id, ", ".join(unexpected) or "a reboot", reply.boot_id)
        conn = dataclasses.replace(conn, stale=True)
    current = measurement_from_codes(
        transfer.codes,
        transfer.volts_per_code,
        fs_hz=record.fs_hz,
        t0_s=record.t0_s,
        view=conn.view,
        channels=transfer.channels,
        excitation_hz=record.excitation_hz,
        cycles=record.cycles,
        temperature_c=transfer.temperature_c,
    )
    node_map = None
    if node_maps and not fill_slot and status.baseline_stored and not conn.stale:
        node_map = _read_node_map(client, reply.measurement_id, conn.slot_measurement_id)
    return Acquisition(
        acquired_at=acquired_at,
        status=status,
        reply=reply,
        transfer=transfer,
        settings=record,
        measurement=current,
        node_map=node_map,
        link_counters={
            "node_crc_errors": status.crc_errors,
            "node_framing_errors": status.framing_errors,
            "node_rejected_requests": status.rejected_requests,
            "client_frame_errors": client.frame_errors,
            "client_retries": client.retried,
            "client_busy_replies": client.busy_replies,
        },
        connection=conn,
        rebooted_from=rebooted_from,
        filled_slot=fill_slot,
        unexpected=unexpected,
    )


def _read_node_map(client: NodeClient, measurement_id: int, baseline_measurement_id: int | None) -> DiMapInput | None:
    try:
        computed = client.compute_di(measurement_id)
        node_map = client.read_di(computed.di_id)
    except NodeClientError as exc:
        log.warning("node DI map not read this cycle: %s: %s", type(exc).__name__, exc)
        return None
    return DiMapInput(
        source=MapSource.NODE,
        method=f"paper-decimated-{node_map.decimation}",
        grid=MapGrid(**node_map.grid.spec()),
        pixels=node_map.pixels.astype(np.float32),
        baseline_measurement_id=baseline_measurement_id,  # the record in the node's baseline slot
    )
