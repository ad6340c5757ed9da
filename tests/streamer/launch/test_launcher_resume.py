"""``ttl run --resume`` and the launcher's journal (streamer.launch.launcher, "Journal and
resuming"): the board an earlier launcher left is cut at the first segment some stage lacks,
and ``ttl inspect`` lists what the journal holds (a killed launcher, stage and router
deaths and restarts)."""

from __future__ import annotations

import io
import json

from streamer.launch.launcher import Launcher, RunOptions
from streamer.runtime.progress import Progress
from streamer.tools.inspect import launcher_journal


def launcher(tmp_path) -> Launcher:
    la = Launcher(RunOptions(run_id="r1", recordings=tmp_path, resume=True), out=io.StringIO())
    la.expected = ["replayer", "tdi_builder", "fitter", "subtractor"]
    la.run_plan = {"segments_total": 10}
    la.run_dir.mkdir(parents=True)
    return la


def board(**handled) -> dict:
    out = {}
    for stage, (done, failed, gaps, fits) in handled.items():
        p = Progress(stage, set(done), set(failed), 10, set(gaps), extra={"fits": set(fits)} if fits else {})
        out[stage] = p.message("r1")
    return out


def test_the_board_is_cut_at_the_first_segment_some_stage_lacks(tmp_path):
    """The replayer and the tdi_builder are ahead of the subtractor, which lacks segment 5:
    every stage goes on from 5 (the caches of the earlier processes died with them, so
    whatever a stage published from 5 on is published again); what each had failed, the
    gaps and the fitter's fits before 5 are kept, nothing from 5 on."""
    la = launcher(tmp_path)
    (la.run_dir / "board.json").write_text(
        json.dumps(
            board(
                replayer=(range(9), (), (), ()),
                tdi_builder=([0, 1, 2, 4, 5, 6, 7], [3], [3], ()),
                fitter=([0, 1, 2, 4, 5, 6], [3], [3], [1, 2, 4, 5, 6]),
                subtractor=([0, 1, 2, 4, 6], [3], [3], ()),
            )
        )
    )
    la.load_board()
    assert la.resumed_from == 5
    assert la.progress["replayer"].done.ranges() == [[0, 4]] and not la.progress["replayer"].failed
    for stage in la.expected[1:]:
        p = la.progress[stage]
        assert p.done.ranges() == [[0, 2], [4, 4]] and p.failed.ranges() == [[3, 3]], (stage, p.message("r1"))
        assert p.gaps.ranges() == [[3, 3]] and p.segments_total == 10
    assert la.progress["fitter"].extra["fits"].ranges() == [[1, 2], [4, 4]]
    assert "fits" not in la.progress["replayer"].extra
    journal = [json.loads(line) for line in (la.run_dir / "launcher.jsonl").read_text().splitlines()]
    assert [(j["kind"], j["first"]) for j in journal] == [("resume", 5)]


def test_a_stage_without_progress_makes_the_run_start_over(tmp_path):
    la = launcher(tmp_path)
    (la.run_dir / "board.json").write_text(json.dumps(board(replayer=(range(9), (), (), ()))))
    la.load_board()
    assert la.resumed_from == 0 and not la.progress


def test_no_board_starts_from_the_first_segment(tmp_path):
    la = launcher(tmp_path)
    la.load_board()
    assert la.resumed_from == 0 and not la.progress
    assert "no " in la.out.getvalue() and "board.json" in la.out.getvalue()


def test_the_board_written_is_the_board_read_back(tmp_path):
    """``save_board`` (after every board publication) and ``load_board`` agree."""
    la = launcher(tmp_path)
    for stage in la.expected:
        la.progress[stage] = Progress(stage, set(range(10)), segments_total=10)
    la.progress["subtractor"] = Progress("subtractor", set(range(7)), segments_total=10)
    la.save_board()
    again = launcher(tmp_path / "again")
    again.run_dir = la.run_dir
    again.load_board()
    assert again.resumed_from == 7
    assert all(p.done.ranges() == [[0, 6]] for p in again.progress.values())


def test_inspect_lists_what_the_journal_holds(tmp_path):
    """A launcher killed (a start without its end), one stage killed and restarted, the
    router killed and restarted, the resume: each is an interruption of ``ttl inspect``; a
    line cut off by the kill is reported, not a crash."""
    records = [
        {"kind": "start", "launcher_pid": 11, "message": "ttl run started (pid 11)"},
        {"kind": "stage-died", "stage": "fitter", "message": "stage fitter (pid 12) died (killed by SIGKILL)"},
        {"kind": "stage-restarted", "stage": "fitter", "message": "stage fitter restarted (pid 13)"},
        {"kind": "router-died", "stage": "router", "message": "the Zenoh router (pid 14) died (killed by SIGKILL)"},
        {"kind": "router-restarted", "stage": "router", "message": "the Zenoh router restarted (pid 15)"},
        {"kind": "start", "launcher_pid": 16, "message": "ttl run started (pid 16) with --resume"},
        {"kind": "resume", "message": "resumed: segments 0..4 handled by every stage; going on from 5"},
        {"kind": "end", "launcher_pid": 16, "message": "ttl run ended (exit status 0)"},
    ]
    text = "\n".join(json.dumps(r) for r in records) + '\n{"kind": "sta'
    (tmp_path / "launcher.jsonl").write_text(text)
    listed = launcher_journal(tmp_path)
    kinds = [(i["stage"], i["kind"]) for i in listed]
    assert kinds == [
        ("fitter", "stage-died"),
        ("fitter", "stage-restarted"),
        ("router", "router-died"),
        ("router", "router-restarted"),
        ("launcher", "launcher-killed"),
        ("launcher", "resume"),
        ("launcher", "journal-unreadable"),
    ], kinds
    assert "pid 11)" in listed[4]["message"] and "without its end record" in listed[4]["message"]
    assert launcher_journal(tmp_path / "nothing") == []


def test_quiet_leaves_out_status_lines_not_what_went_wrong(tmp_path):
    """``ttl run --quiet``: a run's result is its recordings (docs/cli.md, ``--quiet``), so
    the plan, the router line and the summary of a run that succeeded are left out; what
    went wrong (a stage that died, errors) is still said."""
    for quiet, expected in ((False, 2), (True, 1)):
        out = io.StringIO()
        la = Launcher(RunOptions(run_id="r1", recordings=tmp_path, quiet=quiet), out=out)
        la.say("replay: 12 segments", status=True)
        la.say("stage fitter exited with status 1")
        lines = out.getvalue().splitlines()
        assert len(lines) == expected and lines[-1] == "ttl run r1: stage fitter exited with status 1", lines
