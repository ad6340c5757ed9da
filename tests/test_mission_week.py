"""Issue 31's blind week: seven lisainstrument days made by outside code only
(``tests/mission_week.py``: a blind coupling switched on in day 3, lisaglitch's daily glitches,
a lisagwresponse merger, a lisa-gap 7-h gap) through ``ttl run --adopt auto`` at the default
options (``bench/mission.py``'s :func:`run_week`), then everything ``ttl inspect`` reports.

Acceptance (issue 31): the coupling adopted within 24 h of its onset; no coupling adopted
before it and none but one left in the model at the end; the last fit within 0.05 mm/rad of
lisainstrument's coefficients with pull RMS < 1.5; no alert (the truth has no step); every
segment outside the gap has a fit; no glitch older than the one-day window in the last model.

About 25 min of lisainstrument and 20-75 min of replay on 2 cores (the replay's speed is the
mission bench's number), hence the science marker and a long timeout.  ``TTL_WEEK_DAYS``
shortens the week (the times scale; for trying the test, not for its acceptance);
``TTL_WEEK_DIR`` keeps the week there and replays the one an earlier run left.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from mission import run_week  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent / "stages"))
from ttl_testutil import ttl_command  # noqa: E402

MAX_ERROR_MM = 0.05
MAX_PULL_RMS = 1.5
DAYS = float(os.environ.get("TTL_WEEK_DAYS", "7"))


@pytest.mark.science
@pytest.mark.timeout(5 * 3600)
@pytest.mark.parametrize("seed", [31])
def test_a_blind_week_runs_by_itself(tmp_path, seed):
    where = Path(os.environ.get("TTL_WEEK_DIR") or tmp_path)
    week = run_week(where, "lisainstrument", DAYS, seed, timeout=4 * 3600, reuse="TTL_WEEK_DIR" in os.environ)
    print(json.dumps({k: v for k, v in week.items() if k != "model_size_per_fit"}, indent=1))
    assert week["run_exit_status"] == 0, week.get("run_output_tail")
    setup = week["setup"]
    # the coupling: adopted within 24 h of its onset, nothing adopted before, one at the end
    assert week["coupling_adopted_from_segment"] is not None, week["model_changes"]
    assert week["coupling_adopted_from_segment"] - week["coupling_on_segment"] <= 24, week["model_changes"]
    assert week["couplings_adopted_before_the_onset"] == [], week["model_changes"]
    assert len(week["couplings_in_the_model_at_end"]) == 1, (setup["coupling"], week["model_at_end"])
    # the last fit against lisainstrument's coefficients
    assert week["last_fit_max_error_mm_per_rad"] < MAX_ERROR_MM, week["model_at_end"]
    assert week["last_fit_pull_rms"] < MAX_PULL_RMS, week["model_at_end"]
    # the operator's view: no alert, every segment outside the gap fitted, a bounded model
    assert week["alerts"] == []
    assert week["segments_outside_gap_without_fit"] == []
    assert week["glitches_in_the_model_at_end_older_than_a_day"] == []
    assert max(week["model_size_per_fit"].values()) <= 10, week["model_size_per_fit"]

    # everything ttl inspect reports: every stage, no error but the gap's, the gap reported,
    # the model's timeline and each change with who made it
    run_dir = where / "rec" / "mission"
    out = tmp_path / "inspect.json"
    r = subprocess.run(ttl_command("inspect", run_dir, "--json", out), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["stages_missing"] == [] and report["interruptions"] == [], report["stages_missing"]
    assert report["alerts"] == []
    kinds = {(e["stage"], e["kind"]) for e in report["errors"]}
    assert {k for _, k in kinds} <= {"gap"}, sorted(kinds)
    a, b = setup["gap_s"]
    gaps = [(g["t_start"], g["t_stop"]) for g in report["timeline"]["gaps"]]
    assert any(lo <= a + 3600 and hi >= b - 3600 for lo, hi in gaps), (setup["gap_s"], gaps)
    changes = report["model"]["changes"]
    assert changes and all(c.get("by") for c in changes), changes
    warned = sorted({(w["stage"], w["kind"]) for w in report["warnings"]})
    print("warnings:", warned)
    assert not {k for _, k in warned} & {"model-singular", "model-not-fitted"}, warned
