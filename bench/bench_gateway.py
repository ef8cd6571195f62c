"""Gateway ingest benchmark: measurements stored per second with the DI map recomputed.

Each measurement goes through what the gateway's cycle does after the serial transfer: decode
the int16 codes into a Measurement, assess it against the node's baseline (the default
`multipath` method with temperature compensation, and `paper`), decide the verdict
(gateway/decision.py) and store the measurement, its map, detection, events and node health
with `db.cycles.store_cycle` in one SQLite transaction (WAL, synchronous=FULL) on a real file.
16 channels x 6000 samples from the mock node's physics. One thread.
Target (docs/benchmarks.md): >= 20 measurements/s on one core.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from alerts.config import AlertingSettings  # noqa: E402
from alerts.sensor_faults import SensorFaultHistory  # noqa: E402
from db.baselines import set_active_baseline  # noqa: E402
from db.clock import utc_now  # noqa: E402
from db.cycles import store_cycle  # noqa: E402
from db.database import open_database  # noqa: E402
from db.measurement_build import NodeGeometryView, measurement_from_codes  # noqa: E402
from db.measurements import store_measurement  # noqa: E402
from db.models import MeasurementKind, NodeState  # noqa: E402
from db.nodes import upsert_node  # noqa: E402
from db.records import AcquisitionInput, CycleRecord, NodeGeometry, NodeInfo  # noqa: E402
from gateway.assessment import assess_settings, gateway_map  # noqa: E402
from gateway.config import ImagingSettings, NodeSettings  # noqa: E402
from gateway.decision import MonitoringInputs, NodeHistory, decide_monitoring  # noqa: E402
from gateway.flagging import FlagState  # noqa: E402
from imaging.pipeline import assess  # noqa: E402
from mocknode.physics import acquire  # noqa: E402
from mocknode.scenario import load_scenario  # noqa: E402

SCENARIO = Path(__file__).resolve().parent.parent / "examples" / "scenarios" / "paper_notch.toml"


def run(method: str, n: int, workdir: Path) -> tuple[float, float]:
    scn = load_scenario(SCENARIO).nodes[0]
    rng = np.random.default_rng(1)
    healthy = scn.model_copy(update={"defects": []})
    base_acq = acquire(healthy, 0.0, rng)
    currents = [acquire(scn, 10.0 + k, rng) for k in range(8)]
    rings = scn.rings
    geometry = NodeGeometry(
        rx_angles_deg=rings.rx_angles, tx_angles_deg=rings.tx_angles, tx_rx_distance_mm=rings.tx_rx_distance_mm,
        circumference_mm=scn.pipe.outer_circumference_mm, pipe_length_mm=scn.pipe.length_mm,
        tx_axial_mm=rings.tx_axial_mm,
    )
    view = NodeGeometryView(geometry, scn.pipe.velocity_m_s, scn.pipe.wall_mm)
    node = NodeSettings(id="bench", url="loop://", imaging=ImagingSettings(method=method))
    db = open_database(f"sqlite:///{workdir / f'bench-{method}.db'}")

    def build(acq):
        return measurement_from_codes(acq.codes, acq.volts_per_code, fs_hz=acq.fs_hz, t0_s=acq.t0_s, view=view,
                                      channels=None, excitation_hz=85e3, cycles=5, temperature_c=acq.temperature_c)

    common = dict(fs_hz=base_acq.fs_hz, t0_s=base_acq.t0_s, averaging=10, excitation_hz=85e3, cycles=5)
    with db.write() as s:
        upsert_node(s, NodeInfo("bench", "loop://", "1.0.0", 1, 16, 10e6, geometry))
        row = store_measurement(s, "bench", kind=MeasurementKind.BASELINE, acquired_at=utc_now(), node_measurement_id=0,
                                codes=base_acq.codes, volts_per_code=base_acq.volts_per_code, **common)
        set_active_baseline(s, "bench", row.id, created_by="bench", reason="bench")
        baseline_id = row.id
    library = [build(base_acq)]
    history = NodeHistory(NodeState.CALIBRATING, baseline_id, utc_now(), 1)
    inputs = MonitoringInputs(FlagState(), None, [baseline_id], library, SensorFaultHistory(2, (), {}))
    settings = assess_settings(node, None, view.wall_mm)
    alerting = AlertingSettings()
    warm_up = 3  # geometry tables and compiled kernels are built once per process: not timed
    wall0 = cpu0 = 0.0
    for k in range(warm_up + n):
        if k == warm_up:
            wall0, cpu0 = time.perf_counter(), time.process_time()
        acq = currents[k % len(currents)]
        result = assess(build(acq), library, settings)
        verdict = decide_monitoring(node, history, inputs, result, temperature_c=acq.temperature_c, now=utc_now())
        record = CycleRecord(
            acquisition=AcquisitionInput(acquired_at=utc_now(), node_measurement_id=k + 1, codes=acq.codes,
                                         volts_per_code=acq.volts_per_code, **common),
            kind=verdict.kind, error_counters={"cycles": k}, di_maps=[gateway_map(result, [baseline_id])],
            detection=verdict.detection, state_change=verdict.state_change,
        )
        with db.write() as s:
            store_cycle(s, "bench", record,
                        lambda mid: verdict.events(alerting, node_id="bench", measurement_id=mid))  # noqa: B023
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    db.dispose()
    return n / wall, cpu / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=60, help="measurements per method")
    args = parser.parse_args()
    print("gateway ingest: 16 ch x 6000 samples, map recomputed, stored in one SQLite transaction each, one thread")
    with tempfile.TemporaryDirectory() as tmp:
        for method in ("multipath", "paper"):
            rate, cpu_s = run(method, args.n, Path(tmp))
            verdict = "met" if rate >= 20 else "MISSED"
            print(f"  {method:9s}: {rate:6.1f} measurements/s, CPU {cpu_s * 1e3:6.1f} ms per measurement "
                  f"(target >= 20/s: {verdict})")


if __name__ == "__main__":
    main()
