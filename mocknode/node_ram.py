"""The mock node's RAM: a few measurements plus a baseline slot, and the last on-board DI maps.

Each kind has bounded slots that drop their oldest entry (never the baseline); a boot loses
all of it (the node makes a new :class:`NodeRam`). A request for what is not in RAM is refused.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from imaging.grid import Grid
from imaging.measurement import Measurement
from mocknode import physics
from mocknode.refusal import Refused
from protocol.messages import ComputeDiReply, ConfigureReply, ErrorCode

MAX_MEASUREMENTS = 4  # RAM slots, the baseline included (4 x 96 KB of the 512 KB SRAM)
MAX_DI_MAPS = 2
MAX_CHANNELS = 32  # the channel mask is 32 bits wide


@dataclass(frozen=True)
class StoredMeasurement:
    measurement_id: int
    is_baseline: bool
    channel_mask: int
    settings: ConfigureReply  # what it was taken with
    acquisition: physics.Acquisition
    measurement: Measurement  # all enabled channels, full rate


@dataclass(frozen=True)
class StoredDi:
    reply: ComputeDiReply
    grid: Grid
    pixels: np.ndarray  # float32 [n_axial, n_angle]


class NodeRam:
    """What the node holds between requests, from one boot to the next."""

    def __init__(self) -> None:
        self._next_measurement_id = 1
        self.next_di_id = 1
        self._measurements: OrderedDict[int, StoredMeasurement] = OrderedDict()
        self.baseline_id = 0
        self._di_maps: OrderedDict[int, StoredDi] = OrderedDict()

    def __len__(self) -> int:
        """The measurements in RAM, the baseline included."""
        return len(self._measurements)

    def store(self, is_baseline: bool, settings: ConfigureReply, acquisition: physics.Acquisition,
              measurement: Measurement) -> StoredMeasurement:
        """Keep a new measurement under the next id (as the baseline: in the baseline slot)."""
        measurement_id = self._next_measurement_id
        self._next_measurement_id += 1
        stored = StoredMeasurement(measurement_id, is_baseline, settings.channel_mask, settings, acquisition,
                                   measurement)
        if is_baseline:
            self._measurements.pop(self.baseline_id, None)
            self.baseline_id = measurement_id
        self._measurements[measurement_id] = stored
        while len(self._measurements) > MAX_MEASUREMENTS:  # evict the oldest, never the baseline
            oldest = next(k for k in self._measurements if k != self.baseline_id)
            del self._measurements[oldest]
        return stored

    def find(self, measurement_id: int) -> StoredMeasurement | None:
        return self._measurements.get(measurement_id)

    def measurement(self, measurement_id: int) -> StoredMeasurement:
        """A stored measurement; NO_SUCH_MEASUREMENT if it is not in RAM."""
        stored = self._measurements.get(measurement_id)
        if stored is None:
            raise Refused(ErrorCode.NO_SUCH_MEASUREMENT, f"measurement {measurement_id} is not in RAM")
        return stored

    def latest(self) -> StoredMeasurement | None:
        return next(reversed(self._measurements.values()), None)

    def store_di(self, reply: ComputeDiReply, grid: Grid, pixels: np.ndarray) -> None:
        """Keep a DI map under ``reply.di_id`` (``next_di_id``, which moves on)."""
        self.next_di_id += 1
        self._di_maps[reply.di_id] = StoredDi(reply, grid, pixels)
        while len(self._di_maps) > MAX_DI_MAPS:
            self._di_maps.popitem(last=False)

    def di_map(self, di_id: int) -> StoredDi:
        """A stored DI map; NO_SUCH_DI if it is not in RAM."""
        stored = self._di_maps.get(di_id)
        if stored is None:
            raise Refused(ErrorCode.NO_SUCH_DI, f"DI map {di_id} is not in RAM")
        return stored
