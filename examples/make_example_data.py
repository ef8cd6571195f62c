"""Regenerate pipesentry/data/example_*.npz from the mock node's physics (paper notch case).

The baseline is taken defect-free at 22.0 degC, the current measurement with the paper's
20 x 10 x 2 mm notch at 90 deg, 200 mm from the Tx ring, at the same temperature; both with
the scenario's receiver noise (10 averages) and 10-bit quantisation.

    .venv/bin/python examples/make_example_data.py
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from imaging.formats import save_npz
from mocknode.physics import acquire
from mocknode.scenario import load_scenario

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "pipesentry" / "data"


def main() -> None:
    scn = load_scenario(HERE / "scenarios" / "paper_notch.toml").nodes[0]
    fixed_temperature = scn.temperature.model_copy(update={"mean_c": 22.0, "daily_amplitude_c": 0.0, "jitter_c": 0.0})
    scn = scn.model_copy(update={"temperature": fixed_temperature})
    rng = np.random.default_rng(2024)
    healthy = scn.model_copy(update={"defects": []})
    baseline = acquire(healthy, 0.0, rng).to_measurement(healthy)
    current = acquire(scn, 10.0, rng).to_measurement(scn)
    OUT.mkdir(parents=True, exist_ok=True)
    print(save_npz(baseline, OUT / "example_baseline.npz"))
    print(save_npz(current, OUT / "example_current.npz"))


if __name__ == "__main__":
    main()
