"""A restarted fitter told to stop while it rebuilds its window from the recordings
(stages.fitter.model.FitterModel.catch_up) leaves the segment in hand and every later one to
its successor.  The chaos run of seed 825968289: a restarted fitter stopped at 138 of the 167
segments it was pushing again left 167 unhandled, then took 168 with half a window (a time
discontinuity, one FFT segment) and published that fit, 21 % off the clean run's.
A real Fitter, not run (no session); the recorded segments it pushes again are stand-ins."""

from types import SimpleNamespace

import pytest
from ttl_testutil import local_stage_config

import stages.fitter.model as fitter_model
from stages.fitter.fitter import Fitter
from streamer.runtime.lifecycle import StageStopping


def test_a_fitter_stopped_while_rebuilding_its_window_handles_no_later_segment(tmp_path, monkeypatch):
    f = Fitter(local_stage_config("catch-up-stop", 1, tmp_path))
    f._restarted = True
    pushed = []

    def recorded(run_dir, first, log):  # the replayer's recordings hold 0 .. first - 1
        return {i: None for i in range(first)}

    def pushed_again(segments, start, first):  # the stop arrives after 3 segments pushed again
        for i in range(start, first):
            if i == 3:
                f.stop()
            yield SimpleNamespace(index=i), None

    monkeypatch.setattr(fitter_model, "recorded_telemetry", recorded)
    monkeypatch.setattr(fitter_model, "pushed_again", pushed_again)
    real_process = f.process

    def process(header, item):  # the catch-up's own pushes are recorded, not computed
        if f._catching_up:
            pushed.append(header.index)
            return None
        return real_process(header, item)

    monkeypatch.setattr(f, "process", process)
    with pytest.raises(StageStopping, match="rebuilding the window"):
        f.process(SimpleNamespace(index=8), (None, None))
    assert pushed == [0, 1, 2] and not f._caught_up
    for later in (9, 10):  # the window half rebuilt: left to the successor, nothing pushed
        with pytest.raises(StageStopping, match="before the window is rebuilt"):
            f.process(SimpleNamespace(index=later), (None, None))
    assert pushed == [0, 1, 2] and f.rolling is None
