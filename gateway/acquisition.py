"""Acquisition, the node I/O of a cycle: open and configure a node, then STATUS, ACQUIRE, READ_TRACES
and (for a monitor measurement) the node's own map, COMPUTE_DI / READ_DI.

No database and no decisions here: what comes back is typed values that the cycle assesses,
decides on and stores (gateway/worker.py). Whatever checks the node itself (reboots,
re-CONFIGURE, verifying the settings it applied) belongs in this module.
"""
from __future__ import annotations

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
from gateway.node_client import NodeClient, NodeClientError, TraceTransfer
from imaging.measurement import Measurement
from protocol.messages import AcquireReply, ConfigureReply, InfoReply, StatusReply

log = logging.getLogger("pipesentry.gateway")

ClientFactory = Callable[..., NodeClient]


@dataclass(frozen=True)
class Connection:
    """What the gateway knows about a node while its port is open."""

    client: NodeClient
    info: InfoReply
    config: ConfigureReply
    view: NodeGeometryView

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


def open_connection(settings: NodeSettings, client_factory: ClientFactory = NodeClient) -> Connection:
    """Open the node's port, ask INFO and CONFIGURE it; the port is closed again if either fails."""
    s = settings
    client = client_factory(s.url, baudrate=s.baud, timeout_s=s.timeout_s, retries=s.retries)
    try:
        info = client.info()
        config = client.configure(s.excitation_hz, s.cycles, s.averaging, min(s.n_samples, info.max_samples))
    except BaseException:
        client.close()
        raise
    if info.node_id != s.id:
        log.warning("port %s answers as node %r, configured as %r", s.url, info.node_id, s.id)
    return Connection(client, info, config, effective_geometry(info, s.geometry))


@dataclass(frozen=True)
class Acquisition:
    """One measurement as the node delivered it, in codes and in volts, and what the link counted."""

    acquired_at: datetime
    status: StatusReply  # the node's STATUS before it acquired
    reply: AcquireReply
    transfer: TraceTransfer
    averaging: int
    measurement: Measurement  # the traces in volts with the geometry the gateway images with
    node_map: DiMapInput | None  # the node's on-board DI map, when asked for and read
    link_counters: dict[str, int]  # the node's and the client's error counts after this acquisition

    @property
    def temperature_c(self) -> float | None:
        value = self.transfer.temperature_c
        return value if value is not None and math.isfinite(value) else None

    def record(self) -> AcquisitionInput:
        """What storage keeps of it."""
        t = self.transfer
        return AcquisitionInput(
            acquired_at=self.acquired_at,
            node_measurement_id=self.reply.measurement_id,
            codes=t.codes,
            volts_per_code=t.volts_per_code,
            fs_hz=t.fs_hz,
            t0_s=t.t0_s,
            averaging=self.averaging,
            excitation_hz=self.measurement.excitation_hz,
            cycles=self.measurement.cycles,
            temperature_c=self.temperature_c,
            velocity_m_s=self.measurement.velocity_m_s,
            wall_mm=self.measurement.wall_mm,
        )


def acquire(conn: Connection, *, baseline: bool, read_node_map: bool) -> Acquisition:
    """STATUS, ACQUIRE and READ_TRACES; with ``read_node_map`` also the node's own map of it.

    The node's map is for comparison only (the gateway's own map flags damage), so failing to
    read it is logged and the acquisition goes on without it.
    """
    client = conn.client
    status = client.status()
    reply = client.acquire(baseline=baseline)
    acquired_at = utc_now()
    transfer = client.read_traces(reply.measurement_id)
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
    node_map = _read_node_map(client, reply.measurement_id) if read_node_map and status.baseline_stored else None
    return Acquisition(
        acquired_at=acquired_at,
        status=status,
        reply=reply,
        transfer=transfer,
        averaging=conn.config.averaging,
        measurement=current,
        node_map=node_map,
        link_counters={
            "node_crc_errors": status.crc_errors,
            "node_framing_errors": status.framing_errors,
            "node_rejected_requests": status.rejected_requests,
            "client_frame_errors": client.frame_errors,
            "client_retries": client.retried,
        },
    )


def _read_node_map(client: NodeClient, measurement_id: int) -> DiMapInput | None:
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
        baseline_measurement_id=None,
    )
