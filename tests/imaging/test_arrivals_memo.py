"""What imaging derives from a record is kept with the record: no cache shared between node threads.

The issue (14.3): a module-wide LRU of direct-arrival summaries, used from every node's thread
without a lock (get -> move_to_end -> popitem can race into a KeyError) and holding at most 64
records for the whole gateway.
"""
from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict

import numpy as np

import imaging.arrivals as arrivals
from imaging.arrivals import direct_arrival, end_reflection_coefficients
from imaging.measurement import Measurement
from tests.support.synthetic import baseline_and_scatterer


def records(n: int) -> list[Measurement]:
    rng = np.random.default_rng(7)
    base, _ = baseline_and_scatterer(200.0, 90.0)
    out = []
    for _ in range(n):
        traces = base.traces * rng.uniform(0.5, 1.5) + rng.normal(0, 1e-3, base.traces.shape).astype(np.float32)
        out.append(dataclasses.replace(base, traces=traces, pipe_length_mm=1000.0, tx_axial_mm=300.0))
    return out


def summary(m: Measurement) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    arrival = direct_arrival(m)
    return arrival.amplitude.copy(), arrival.time_s.copy(), end_reflection_coefficients(m)


def test_the_imaging_layer_holds_no_module_wide_cache():
    caches = [name for name, value in vars(arrivals).items()
              if not name.startswith("__") and isinstance(value, dict | OrderedDict | list | set)]
    assert caches == []


def test_many_threads_on_many_records_all_get_what_a_fresh_computation_gives():
    # More records than the old LRU held (64), each analysed from 8 threads at once, interleaved.
    shared = records(80)
    expected = [summary(dataclasses.replace(m)) for m in shared]  # fresh copies: nothing derived yet
    errors: list[BaseException] = []
    mismatches: list[int] = []
    start = threading.Barrier(8)

    def work(offset: int) -> None:
        try:
            start.wait(timeout=30)
            for round_ in range(3):
                for i in range(len(shared)):
                    k = (i * 7 + offset + round_) % len(shared)
                    got = summary(shared[k])
                    want = expected[k]
                    if not (np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[2] == want[2]):
                        mismatches.append(k)
        except BaseException as exc:  # noqa: BLE001 (reported below: any error fails the test)
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads)
    assert errors == [] and mismatches == []


def test_a_record_remembers_its_summary_and_a_copy_starts_afresh():
    (m,) = records(1)
    first = direct_arrival(m)
    assert direct_arrival(m) is first  # derived once, kept with the record
    assert direct_arrival(dataclasses.replace(m)) is not first  # a new record derives its own


def test_traces_changed_in_place_are_analysed_again():
    (m,) = records(1)
    before = direct_arrival(m).amplitude.copy()
    np.multiply(m.traces, 2.0, out=m.traces)
    after = direct_arrival(m).amplitude
    np.testing.assert_allclose(after, 2.0 * before, rtol=1e-5)
