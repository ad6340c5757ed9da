"""A stage told to stop leaves its live diagnosis between two steps (stages.fitter.live_diagnosis.stop_check).

A day-long diagnosis runs for minutes in the fitter's loop, which polls its stop flag only
between segments: a mission week's fitter went on diagnosing for over 2 min after its
launcher was gone.  The diagnosis calls its ``checkpoint`` callback before each step, each
candidate and each transient event; the fitter's raises once the stage is stopping, and the
diagnosis' candidate threads end with it.
"""

import threading

import pytest

from stages.fitter.live_diagnosis import DiagnosisStopped, stop_check
from ttlcore.diagnose.diagnoser import diagnose
from ttlcore.diagnose.settings import DiagnoseSettings
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


def test_a_stop_during_the_candidates_ends_the_diagnosis_before_the_next_candidate():
    # one step can last minutes on a loaded machine (a day's candidates one at a time, the
    # transient events' glitch searches): the chaos test once saw a fitter outlive its killed
    # launcher by more than 60 s in one.  ``checkpoint`` is also called before each candidate
    # (and each transient event): the diagnosis stops at the first one after the stop.
    tm, _ = simulate(SimulationConfig(duration=6 * 3600.0, orbit="keplerian", seed=31), chunk_size=6 * 3600 * 4)
    seen: list[str] = []
    stop = threading.Event()
    check = stop_check(stop.is_set)

    def checkpoint(step: str) -> None:
        seen.append(step)
        if sum(s.startswith("candidate ") for s in seen) == 2:
            stop.set()  # while the second candidate is about to be scored
        check(step)

    with pytest.raises(DiagnosisStopped, match="before the diagnosis' 'candidate "):
        diagnose(tm, checkpoint=checkpoint, witnesses=False, settings=DiagnoseSettings(workers=1))
    assert [s for s in seen if not s.startswith("candidate ")] == ["TDI and spectra", "fit", "noise model"]
    assert sum(s.startswith("candidate ") for s in seen) == 2, seen
