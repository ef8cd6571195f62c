"""A dense ring's defect placed by its echoes is fitted along every leg round the pipe that arrives within the
record (imaging/multidefect.py ``fit_wraps``), checked on the project's own full-wave engine (fullwave/, which
shares no code with the imaging's path model), on a coarse 2 mm grid so that each record takes about a second."""
import dataclasses

import numpy as np
import pytest

import imaging.multidefect as multidefect
from fullwave.defects import Notch
from fullwave.record import PipeModel, SimulationSpec, simulate
from fullwave.transducers import RingLayout
from imaging.analysis import analyze
from imaging.echofit import fit_smooth_echoes
from imaging.multidefect import FIT_WRAPS, fit_wraps
from imaging.multipath import path_model_for
from imaging.paths import wrap_turns
from imaging.scene import Scene
from imaging.timing import MM_PER_M

WALL_MM = 4.0  # the engine's default wall: its wave wraps at pi (OD - wall)


def _ring(n_transducers: int = 16, excitation_hz: float = 85e3) -> SimulationSpec:
    return SimulationSpec(pipe=PipeModel(length_mm=700.0, ends="absorbing", wall_mm=WALL_MM),
                          rings=RingLayout(tx_axial_mm=150.0, n_transducers=n_transducers, tx_rx_distance_mm=400.0),
                          excitation_hz=excitation_hz, cell_mm=2.0, n_samples=6000)


@pytest.fixture(scope="module")
def sound_pipe():
    return simulate(_ring())


def _left_at_truth(baseline, notch: Notch, wraps: int) -> float:
    """What the shared echo fit at the notch's true position, along ``wraps`` legs, leaves of its record."""
    current = simulate(_ring().with_changes(defects=(notch,)))
    residual = baseline.traces.astype(np.float64) - current.traces
    model = dataclasses.replace(path_model_for(baseline, wall_mm=WALL_MM), wraps=wraps)
    fitted = fit_smooth_echoes(residual, Scene.of(baseline, model), [(notch.axial_mm, notch.angle_deg)])[0]
    return float(np.sum((residual - fitted)**2) / np.sum(residual**2))


@pytest.mark.parametrize("notch", [Notch(150.0, 30.0), Notch(250.0, 200.0), Notch(150.0, 30.0, depth_mm=0.5)],
                         ids=lambda n: f"{n.axial_mm:g}mm-{n.angle_deg:g}deg-{n.depth_mm:g}deep")
def test_a_notchs_echoes_keep_circling_the_pipe_for_the_whole_record(sound_pipe, notch):
    # Without end echoes most of what six legs leave is the scattered wave's later turns (measured:
    # 0.27 / 0.21 / 0.37 of the record along six legs, 0.07 / 0.06 / 0.06 along all eleven that arrive).
    scene = Scene.of(sound_pipe, path_model_for(sound_pipe, wall_mm=WALL_MM))
    every_leg = fit_wraps(scene, sound_pipe.traces.shape[1])
    assert every_leg > FIT_WRAPS
    left_six, left_all = _left_at_truth(sound_pipe, notch, FIT_WRAPS), _left_at_truth(sound_pipe, notch, every_leg)
    assert left_all < 0.5 * left_six
    assert left_all < 0.1


def test_further_legs_than_those_that_arrive_within_the_record_explain_nothing_more(sound_pipe):
    scene = Scene.of(sound_pipe, path_model_for(sound_pipe, wall_mm=WALL_MM))
    every_leg = fit_wraps(scene, sound_pipe.traces.shape[1])
    notch = Notch(150.0, 30.0)
    assert _left_at_truth(sound_pipe, notch, every_leg + 4) == pytest.approx(_left_at_truth(sound_pipe, notch, every_leg),
                                                                             rel=1e-6)


def _shortest_arc_mm(leg: int, circumference_mm: float) -> float:
    """The shortest circumferential arc leg ``leg`` can take (the shorter way's arc lies in [0, C / 2])."""
    turns = wrap_turns(leg)
    return turns * circumference_mm if turns >= 0 else (-turns - 0.5) * circumference_mm


def test_no_leg_that_can_arrive_within_the_record_is_left_out(sound_pipe):
    scene = Scene.of(sound_pipe, path_model_for(sound_pipe, wall_mm=WALL_MM))
    circumference = scene.model.circumference_mm
    counts = []
    for n_samples in (2000, 4000, 6000, 9000):
        longest = (scene.t0_s + n_samples / scene.fs_hz) * scene.velocity_m_s * MM_PER_M
        legs = fit_wraps(scene, n_samples)
        assert all(_shortest_arc_mm(leg, circumference) > longest for leg in range(legs, legs + 6))
        assert legs == FIT_WRAPS or _shortest_arc_mm(legs - 2, circumference) <= longest  # none needlessly
        counts.append(legs)
    assert counts == sorted(counts) and counts[-1] > counts[0]


def test_a_sparse_rings_element_model_keeps_its_fixed_legs():
    baseline = simulate(dataclasses.replace(_ring(8, 75e3), n_samples=3000))
    scene = Scene.of(baseline, path_model_for(baseline))
    assert scene.model.elements
    assert fit_wraps(scene, 6000) == FIT_WRAPS == fit_wraps(scene, 60000)


def test_a_notch_without_end_echoes_is_placed_along_every_leg_while_the_search_keeps_six(sound_pipe, monkeypatch):
    legs_fitted: list[int] = []
    fit = multidefect.fit_smooth_echoes

    def spy(residual, scene, positions, **kwargs):
        legs_fitted.append(scene.model.wraps)
        return fit(residual, scene, positions, **kwargs)

    monkeypatch.setattr(multidefect, "fit_smooth_echoes", spy)
    notch = Notch(150.0, 30.0)
    result = analyze(sound_pipe, simulate(_ring().with_changes(defects=(notch,))), wall_mm=WALL_MM)
    every_leg = fit_wraps(Scene.of(sound_pipe, path_model_for(sound_pipe, wall_mm=WALL_MM)),
                          sound_pipe.traces.shape[1])
    assert len(result.defects) == 1 and abs(result.defects[0].angle_deg - notch.angle_deg) < 5.0
    assert legs_fitted.count(every_leg) >= 10  # the placement's trial positions along the line and round the pipe
    assert set(legs_fitted) <= {every_leg, FIT_WRAPS, 2}  # the search's fits, the strong-change judgment's two
