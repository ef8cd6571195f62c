"""The acquisition settings a record was taken with, and when two records can be compared (pure).

A record is stored with what the node says it was taken with (protocol version 2 states it in
ACQUIRE_REPLY and TRACE_META; with a version-1 node, what its CONFIGURE_REPLY applied in the
same boot), never with what the gateway asked for. Two records whose settings differ are never
imaged against each other: a different excitation, averaging (noise), record length, channel
set or time axis is a different measurement, not a change of the pipe.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from protocol.messages import AcquireReply, ConfigureReply, ConfigureRequest


@dataclass(frozen=True)
class RecordSettings:
    """What decides whether two records are comparable."""

    excitation_hz: float
    cycles: int
    averaging: int
    n_channels: int
    n_samples: int
    fs_hz: float
    t0_s: float

    def describe(self) -> str:
        return (f"{self.excitation_hz / 1e3:g} kHz x {self.cycles} cycles, averaging {self.averaging}, "
                f"{self.n_channels} channels x {self.n_samples} samples at {self.fs_hz / 1e6:g} MHz")


class SettingsNotStated(ValueError):
    """The node's reply lacks what a version-2 record must state (a CRC-valid but incomplete reply)."""


def _same(a: float | int, b: float | int) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return bool(np.float32(a) == np.float32(b))  # the wire carries f32
    return a == b


def differences(record: RecordSettings, reference: RecordSettings, reference_name: str = "baseline") -> list[str]:
    """Each setting in which ``record`` differs from ``reference``, e.g. ``averaging 1 (baseline 10)``."""
    out = []
    for f in fields(RecordSettings):
        a, b = getattr(record, f.name), getattr(reference, f.name)
        if not _same(a, b):
            out.append(f"{f.name} {a:g} ({reference_name} {b:g})")
    return out


def stated_settings(reply: AcquireReply, *, n_channels: int, n_samples: int, t0_s: float) -> RecordSettings:
    """The settings a version-2 ACQUIRE_REPLY states (channels and length as read, t0 from TRACE_META)."""
    if reply.excitation_hz is None or reply.cycles is None or reply.averaging is None or reply.fs_hz is None:
        raise SettingsNotStated(f"ACQUIRE_REPLY of measurement {reply.measurement_id} does not state its settings")
    return RecordSettings(float(reply.excitation_hz), int(reply.cycles), int(reply.averaging), n_channels,
                          n_samples, float(reply.fs_hz), float(t0_s))


def applied_settings(config: ConfigureReply, *, fs_hz: float, t0_s: float) -> RecordSettings:
    """The settings a CONFIGURE_REPLY put in force (what a version-1 node records with until it reboots)."""
    return RecordSettings(float(config.excitation_hz), int(config.cycles), int(config.averaging),
                          int(config.channel_mask).bit_count(), int(config.n_samples), float(fs_hz), float(t0_s))


def configure_problems(asked: ConfigureRequest, applied: ConfigureReply) -> list[str]:
    """How the settings the node applied differ from the ones asked for (a conformant node never
    differs: it applies or refuses, docs/protocol.md R-CONF-2)."""
    out = []
    for name in ("excitation_hz", "cycles", "averaging", "channel_mask", "n_samples"):
        a, b = getattr(asked, name), getattr(applied, name)
        if not _same(a, b):
            out.append(f"{name}: the node applied {b:g}, the gateway asked for {a:g}")
    return out


def comparable(record: RecordSettings, library: Sequence[RecordSettings]) -> tuple[list[int], str | None]:
    """Indices of the library baselines ``record`` can be imaged against, and, when there are
    none, why (naming how it differs from the first, the active baseline)."""
    keep = [i for i, settings in enumerate(library) if not differences(record, settings)]
    if keep or not library:
        return keep, None
    return keep, ("settings differ from every baseline's: " + ", ".join(differences(record, library[0]))
                  + " (a record is only imaged against baselines taken with its settings)")
