"""Onsets (ttlcore.diagnose.onsets): an excess that lasts to the data's end is a change that
has not ended, not a transient to gate.

The unit tests class report entries by hand.  The science test injects, with code of its
own, a coupling the diagnosis does not name (the blind generator's witness, filtered and
delayed, :func:`test_diagnose_blind_lisainstrument.injected_eta`) into the last hours of
16 h of a lisainstrument day, switched on at a random time: the shape of a live window
diagnosed a few hours after a coupling appeared (issue 31: a mission week's coupling was
gated twice and adopted 24 h after its onset).
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ttlcore.diagnose.onsets import ONSET, ONSET_MIN_HOURS, onset_events, reclassify_onsets

sys.path.insert(0, str(Path(__file__).parent))

HOUR = 3600.0


def _event(t_start, t_stop, cls="noise-change", t_share=0.3):
    return {
        "class": cls,
        "t_start": t_start,
        "t_stop": t_stop,
        "duration": t_stop - t_start,
        "evidence": [],
        "t_share": t_share,
        "t_share_threshold": 0.006,
    }


def test_an_event_that_lasts_to_the_end_is_an_onset_and_others_keep_their_class():
    end, tile, hop = 16 * HOUR, 900.0, 450.0
    events = [
        _event(12.0 * HOUR, end - 0.2 * HOUR),  # to the end (within a tile and a hop): an onset
        _event(3.0 * HOUR, 9.0 * HOUR),  # ended: a noise change, gated as before
        _event(end - 0.5 * HOUR, end - 0.1 * HOUR, "glitch"),  # at the end but short: a glitch
        _event(12.0 * HOUR, end, "gravitational-wave"),  # a signal stays a signal
        _event(12.0 * HOUR, end, "gap"),  # so does missing data
        _event(end - ONSET_MIN_HOURS * HOUR - 60.0, end - 60.0, "unclassified"),  # just long enough
        _event(9.0 * HOUR, end, "noise-change", t_share=0.001),  # T empty: an inspiral building up
    ]
    reclassify_onsets(events, end, tile, hop)
    assert [e["class"] for e in events] == [
        ONSET,
        "noise-change",
        "glitch",
        "gravitational-wave",
        "gap",
        ONSET,
        "noise-change",
    ]
    assert "was noise-change" in events[0]["evidence"][-1] and events[1]["evidence"] == []
    assert onset_events(events) == [events[0], events[5]]


@pytest.mark.science
@pytest.mark.timeout(3600)
def test_a_coupling_that_switches_on_is_advised_switched_on_and_never_gated(tmp_path):
    from lisainstrument_sim import simulate_lisainstrument
    from test_diagnose_blind import MAX_ERROR, MAX_PULL_RMS, blind_case
    from test_diagnose_blind_lisainstrument import (
        follow_advice,
        injected_eta,
        scaled_to_a_random_level,
    )

    from ttlcore.conventions import COEFFICIENT_NAMES
    from ttlcore.io.lisainstrument import lisainstrument_truth
    from ttlcore.io.reader import read_telemetry
    from ttlcore.io.telemetry import write_telemetry

    li = tmp_path / "li.h5"
    simulate_lisainstrument(li, duration=16 * HOUR, orbits="keplerian", seed=8)
    truth = lisainstrument_truth(li)
    c_true = np.array([truth[n] for n in COEFFICIENT_NAMES])
    tm = read_telemetry(li)
    seed = 27  # the blind generator's case (a witness of a random MOSA and angle, filtered, delayed)
    rng = np.random.default_rng(seed)
    t_on = float(tm.t0 + rng.uniform(10.5, 12.5) * HOUR)  # 3.5-5.5 h before the end
    t = tm.t0 + np.arange(tm.size) / tm.fs
    extra = scaled_to_a_random_level(tm, injected_eta(tm, blind_case(seed)), seed) * (t >= t_on)
    path = write_telemetry(tmp_path / "window.h5", replace(tm, eta=tm.eta + extra, source="memory"))
    reports = follow_advice(path, tmp_path)
    first, last = reports[0], reports[-1]
    events = first["transients"]["events"]
    onsets = [e for e in events if e["class"] == ONSET]
    advice = first["recommendation"]
    summary = (
        blind_case(seed),
        t_on / HOUR,
        [(e["class"], e["t_start"] / HOUR) for e in events],
        advice.get("message"),
    )
    assert onsets and abs(onsets[0]["t_start"] - t_on) < 1800.0, summary
    # the coupling advised switched on, at its onset; nothing gated over its hours
    assert "vary=step" in advice["cli_spec"] and "gate" not in advice["cli_spec"], summary
    t_step = float(advice["cli_spec"].split("t_step=")[1].split("s")[0])
    assert abs(t_step - t_on) < 900.0, (t_step / HOUR, t_on / HOUR)
    bands = last["adequacy"]["bands"]
    assert not any(b["fails"] for b in bands), [round(b["chi2_dof"], 3) for b in bands]
    c = last["model"]["coefficients"]
    err = np.array([c["values"][n] for n in COEFFICIENT_NAMES]) - c_true
    pull = err / np.array([c["sigma"][n] for n in COEFFICIENT_NAMES])
    print(
        f"{summary}: advised {advice['cli_spec']}; last fit {1e3 * np.max(np.abs(err)):.4f} mm/rad, "
        f"pull RMS {np.sqrt(np.mean(pull**2)):.2f}"
    )
    assert np.max(np.abs(err)) < MAX_ERROR and np.sqrt(np.mean(pull**2)) < MAX_PULL_RMS
