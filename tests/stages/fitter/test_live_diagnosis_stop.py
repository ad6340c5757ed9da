"""A stage told to stop leaves its live diagnosis between two steps (stages.fitter.live_diagnosis.stop_check).

A day-long diagnosis runs for minutes in the fitter's loop, which polls its stop flag only
between segments: a mission week's fitter went on diagnosing for over 2 min after its
launcher was gone.  The diagnosis calls its ``progress`` callback before each step; the
fitter's raises once the stage is stopping, and the diagnosis' candidate threads end with it.
"""

import threading

import pytest

from stages.fitter.live_diagnosis import DiagnosisStopped, stop_check
from ttlcore.diagnose.diagnoser import diagnose
from ttlcore.sim.simulator import SimulationConfig, simulate


def test_a_stopping_stage_abandons_its_diagnosis_at_the_next_step_and_leaves_no_thread():
    tm, _ = simulate(SimulationConfig(duration=6 * 3600.0, orbit="keplerian", seed=31), chunk_size=6 * 3600 * 4)
    steps: list[str] = []
    stop = threading.Event()

    def stopping() -> bool:
        return stop.is_set()

    check = stop_check(stopping)

    def progress(step: str) -> None:
        steps.append(step)
        if step == "witness search":  # the candidate threads are scoring by now
            stop.set()
        check(step)

    before = threading.active_count()
    with pytest.raises(DiagnosisStopped, match="witness search"):
        diagnose(tm, progress=progress)
    # the steps before it ran, none after; the pool's threads are gone with it
    assert steps == ["TDI and spectra", "fit", "noise model", "witness search"], steps
    assert threading.active_count() == before
    # a stage not stopping: the callback lets every step through
    stop_check(lambda: False)("candidates")
