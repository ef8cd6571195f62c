"""Test-only: ``pipesentry mock-node`` whose faults and defects come and go when a test says so.

``python tests/support/mock_on_demand.py <mock-node options>``, with either or both of:

* ``PIPESENTRY_TEST_DEAD_RX_FILE`` naming a file: while it exists, the receivers listed in it
  (comma-separated rx indices) keep 2 % of their signal, as a debonded transducer or a cut cable
  would; without it the node is healthy.
* ``PIPESENTRY_TEST_DEFECTS_FILE`` naming a file: the scenario's defects are in the pipe while it
  exists (from the first acquisition after it appeared) and not before.

The test creates and removes the files, so nothing depends on timing. The scenario's own
``receiver_faults`` and ``appears_at_s`` follow scenario time, which a test cannot line up with
the gateway's measurements exactly (commissioning and calibration take as long as the machine
makes them); hence this wrapper around the acquisition.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import typer

from mocknode import physics
from mocknode.cli import mock_node
from mocknode.scenario import NodeScenario

LEFT = 0.02  # of the signal a dead receiver still delivers (amplitude ratio < 0.1: "no_signal")
_acquire = physics.acquire


def _control(variable: str) -> Path | None:
    value = os.environ.get(variable)
    return Path(value) if value else None


DEAD_RX = _control("PIPESENTRY_TEST_DEAD_RX_FILE")
DEFECTS = _control("PIPESENTRY_TEST_DEFECTS_FILE")


def dead_receivers() -> list[int]:
    if DEAD_RX is None:
        return []
    try:
        text = DEAD_RX.read_text()
    except FileNotFoundError:
        return []
    return [int(part) for part in text.split(",") if part.strip()]


def with_defects_on_demand(scn: NodeScenario) -> NodeScenario:
    if DEFECTS is None:
        return scn
    if not DEFECTS.exists():
        return scn.model_copy(update={"defects": []})
    return scn.model_copy(update={"defects": [d.model_copy(update={"appears_at_s": 0.0}) for d in scn.defects]})


def acquire_on_demand(scn: NodeScenario, elapsed_s: float, rng: np.random.Generator) -> physics.Acquisition:
    acquisition = _acquire(with_defects_on_demand(scn), elapsed_s, rng)
    dead = dead_receivers()
    if not dead:
        return acquisition
    codes = acquisition.codes.copy()
    codes[dead] = np.round(codes[dead] * LEFT).astype(codes.dtype)
    return dataclasses.replace(acquisition, codes=codes)


if __name__ == "__main__":
    physics.acquire = acquire_on_demand  # mocknode/measuring.py calls physics.acquire(...)
    typer.run(mock_node)
