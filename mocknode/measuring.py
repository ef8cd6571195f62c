"""One acquisition of the mock node: the pipe simulated by ``physics.acquire`` (looked up at each
call: a test may replace it), or a full-wave record replayed (``mocknode/recorded.py``), kept
for the receivers the channel mask enables only, as the FPGA does."""
from __future__ import annotations

import dataclasses

import numpy as np

from imaging.measurement import Measurement
from mocknode import physics
from mocknode.recorded import RecordedPipe, acquire_recorded
from mocknode.scenario import NodeScenario


def acquire(scn: NodeScenario, channel_mask: int, recorded: RecordedPipe | None, elapsed_s: float,
            rng: np.random.Generator) -> tuple[physics.Acquisition, Measurement]:
    """The codes and the measurement of the enabled receivers at ``elapsed_s`` of scenario time
    (``scn`` with the node's settings applied)."""
    if recorded is not None:
        acquisition = acquire_recorded(scn, recorded, elapsed_s, rng)
    else:
        acquisition = physics.acquire(scn, elapsed_s, rng)
    rows = [i for i in range(len(scn.rings.rx_angles)) if channel_mask >> i & 1]
    full = acquisition.to_measurement(scn)
    if full.n_rx != len(rows):  # keep only the enabled receivers, as the FPGA does
        full = dataclasses.replace(full, traces=full.traces[rows], rx_angles_deg=full.rx_angles_deg[rows])
        acquisition = dataclasses.replace(acquisition, codes=np.ascontiguousarray(acquisition.codes[rows]))
    return acquisition, full
