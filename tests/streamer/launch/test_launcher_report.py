"""The final report of ``ttl run`` (streamer.launch.launcher.Launcher.report): exit statuses."""

from __future__ import annotations

import io

from streamer.launch.launcher import Launcher, RunOptions
from streamer.runtime.progress import Progress
from streamer.runtime.rangeset import RangeSet


def launcher(tmp_path, errors=()) -> tuple[Launcher, io.StringIO]:
    out = io.StringIO()
    la = Launcher(RunOptions(run_id="r1", recordings=tmp_path), out=out)
    la.expected = ["replayer", "fitter"]
    la.run_plan = {"segments_total": 3}
    for stage in la.expected:
        p = Progress(stage, segments_total=3)
        p.done.update(range(3))
        if stage == "fitter":  # every segment produced a fit (else segments are lost: exit 3)
            p.extra["fits"] = RangeSet(range(3))
        la.progress[stage] = p
    la.errors = list(errors)
    return la, out


def conflict(index: int, first_copy: str) -> dict:
    return {
        "stage": "fitter",
        "kind": "conflict",
        "index": index,
        "key": f"ttl/r1/tdi/{index}",
        "field": "payload",
        "message": "conflicting copies",
        "details": {"first_copy": first_copy},
    }


def test_a_complete_run_exits_0(tmp_path):
    la, out = launcher(tmp_path, [{"stage": "fitter", "kind": "rejected", "index": 1, "key": "ttl/r1/tdi/1"}])
    assert la.report(None) == 0, out.getvalue()
    assert "done: 3 segments" in out.getvalue()


def test_conflicting_copies_make_the_run_exit_1_even_when_the_first_copy_was_used(tmp_path):
    """docs/operations.md: two different copies of a segment were published; whichever was
    used, one was not the producer's, and ``ttl run`` exits 1 (it exited 0 when every
    segment was handled anyway)."""
    la, out = launcher(tmp_path, [conflict(1, "used"), conflict(1, "used"), conflict(2, "withdrawn")])
    assert la.report(None) == 1
    text = out.getvalue()
    assert "conflicting copies of 2 segment(s) received: tdi/1, tdi/2" in text and "done:" not in text, text
    assert "ended (exit status 1): 3 segments, 3 error report(s)" in text and "0 progress message(s) refused" in text
