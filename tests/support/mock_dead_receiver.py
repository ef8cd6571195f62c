"""Test-only: ``pipesentry mock-node`` whose receivers die while a control file says so.

``python tests/mock_dead_receiver.py <mock-node options>`` with ``PIPESENTRY_TEST_DEAD_RX_FILE``
naming a file: while it exists, the receivers listed in it (comma-separated rx indices) keep
2 % of their signal, as a debonded transducer or a cut cable would; without it the node is
healthy. The test creates and removes the file, so nothing depends on timing. The scenario's
own ``receiver_faults`` follow scenario time, which a test cannot line up with the gateway's
measurements exactly; hence this wrapper around the acquisition.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import typer

from mocknode import physics
from mocknode.cli import mock_node

CONTROL = Path(os.environ["PIPESENTRY_TEST_DEAD_RX_FILE"])
LEFT = 0.02  # of the signal a dead receiver still delivers (amplitude ratio < 0.1: "no_signal")
_acquire = physics.acquire


def dead_receivers() -> list[int]:
    try:
        text = CONTROL.read_text()
    except FileNotFoundError:
        return []
    return [int(part) for part in text.split(",") if part.strip()]


def acquire_with_dead_receivers(scn, elapsed_s: float, rng: np.random.Generator) -> physics.Acquisition:
    acquisition = _acquire(scn, elapsed_s, rng)
    dead = dead_receivers()
    if not dead:
        return acquisition
    codes = acquisition.codes.copy()
    codes[dead] = np.round(codes[dead] * LEFT).astype(codes.dtype)
    return dataclasses.replace(acquisition, codes=codes)


if __name__ == "__main__":
    physics.acquire = acquire_with_dead_receivers  # mocknode/node.py calls physics.acquire(...)
    typer.run(mock_node)
