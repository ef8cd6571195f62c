"""Fault injection switches for the mock node (per node, from the scenario or the command line).

Two kinds: faults of a field installation (line noise, stalls, unplugged cables, power cuts),
which a conformant node suffers and the gateway must survive; and ``violations``, each of
which makes the node break one numbered requirement of docs/protocol.md, so that
``pipesentry node-check`` can be shown to catch it on the line of that requirement.
"""
from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field


class Violation(StrEnum):
    """A deliberate departure from docs/protocol.md, named with the requirement it breaks."""

    ANSWERS_CORRUPT_FRAMES = "answers_corrupt_frames"  # R-FRAME-2: answers a frame whose CRC is wrong
    ACCEPTS_OVERSIZED = "accepts_oversized"  # R-FRAME-3: decodes a frame longer than MAX_FRAME_BYTES
    INFO_NEEDS_VERSION = "info_needs_version"  # R-VER-1: BAD_VERSION to an INFO of another version
    VERSION_IGNORED = "version_ignored"  # R-VER-2: runs requests of versions it does not speak
    REQUEST_ID_ZERO_RUNS = "request_id_zero_runs"  # R-REQ-1: runs a request with request_id 0
    LENIENT_LENGTHS = "lenient_lengths"  # R-REQ-3: ignores bytes after a request's documented length
    CLAMPS_SETTINGS = "clamps_settings"  # R-CONF-2: clamps n_samples/averaging instead of refusing
    ACQUIRES_TWICE = "acquires_twice"  # R-CACHE-1: a resent ACQUIRE acquires again
    CACHED_CRC_STALE = "cached_crc_stale"  # R-CACHE-2: a replay sets CACHED but keeps the original CRC
    CACHES_ERRORS = "caches_errors"  # R-CACHE-3: replays an ERROR reply from the cache
    MISSTATES_CHUNK_COUNT = "misstates_chunk_count"  # R-TRACE-1: each BULK_CHUNK states one chunk more than META
    IGNORES_CHUNK_LIST = "ignores_chunk_list"  # R-BULK-1: sends every chunk when asked for some
    DI_BOXCAR_DECIMATION = "di_boxcar_decimation"  # R-DI-2: decimates by block averages, not subsampling
    BUSY_FOREVER = "busy_forever"  # R-BUSY-1: once BUSY, it never serves a command again (until reboot)
    BOOT_ID_STICKY = "boot_id_sticky"  # R-BOOT-2: keeps its boot id across a power cycle


class FaultSpec(BaseModel):
    """Each fault is off by default. Rates are probabilities per byte sent by the node."""

    model_config = ConfigDict(extra="forbid")

    corrupt_byte_rate: float = Field(0.0, ge=0.0, le=1.0, description="flip one random bit of a sent byte")
    drop_byte_rate: float = Field(0.0, ge=0.0, le=1.0, description="silently drop a sent byte")
    stall_probability: float = Field(0.0, ge=0.0, le=1.0, description="per request: do not answer for stall_s")
    stall_s: float = Field(0.0, ge=0.0, description="length of a stall in seconds")
    disconnect_every_s: float = Field(0.0, ge=0.0, description="close the port and open a new one every N s (0=never)")
    reconnect_after_s: float = Field(1.0, ge=0.0, description="how long the port stays gone when disconnected")
    reboot_probability: float = Field(
        0.0, ge=0.0, le=1.0, description="per bulk frame sent: reboot mid-transfer, losing all RAM state"
    )
    reboot_every_s: float = Field(
        0.0, ge=0.0, description="power-cycle the node every N s between requests, the port staying open (0=never): "
        "a brown-out; it comes back with its power-up settings"
    )
    garbage_on_power_up: int = Field(0, ge=0, description="bytes of random garbage sent at (re)boot")
    busy_probability: float = Field(
        0.0, ge=0.0, lt=1.0, description="per request other than INFO/STATUS: answer ERROR BUSY (transient, allowed)"
    )
    protocol_version: int | None = Field(
        None, ge=1, le=255, description="speak only this protocol version (1: a version-1 node as that version "
        "specified it; above the newest: a node of a future version)"
    )
    violations: list[Violation] = Field(default_factory=list, description="requirements of docs/protocol.md to break")
