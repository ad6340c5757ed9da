"""Unit tests of :mod:`streamer.tools.inspect_interruptions`: what ``ttl inspect`` lists as gone
wrong, from the stages' file summaries (dicts as :func:`streamer.tools.inspect.inspect_run`
builds them), a real recording and a launcher journal on disk (no bus)."""

import json

from streamer.recording.recorder import Recorder, read_recording
from streamer.tools.inspect_interruptions import interruptions, stage_interruptions


def summary(name, **kw):
    f = {
        "file": name,
        "readable": True,
        "complete": True,
        "stopped": True,
        "completed": True,
        "problem": None,
        "records": 10,
        "incomplete_segments": [],
    }
    return f | kw


def test_each_file_says_what_went_wrong(tmp_path):
    rec = Recorder(tmp_path / "fitter.mcap", metadata={"run": "r1", "stage": "fitter", "class": "X", "config": "{}"})
    rec.write_json("events", {"kind": "restored", "message": "window rebuilt from the replayer's recording"})
    rec.close()
    files = [
        summary("fitter.1.mcap", complete=False, stopped=False, problem="no footer", records=7),
        summary("fitter.2.mcap", problem="bad chunk at 1234"),
        summary("fitter.3.mcap", stopped=False, incomplete_segments=[{"topic": "fit", "index": 5}]),
        summary("fitter.4.mcap", readable=False, problem="fitter.4.mcap: not an MCAP file"),
        summary(
            "fitter.5.mcap",
            complete=False,
            problem="no footer",
            stop_note={"reason": "disk-full", "message": "disk full"},
        ),
        summary("fitter.mcap", stop_event={"message": "the launcher is gone", "details": {"orphaned": True}}),
    ]
    out = stage_interruptions("fitter", {"files": files, "restarts": 5}, [read_recording(tmp_path / "fitter.mcap")])
    assert [(x["kind"], x.get("file")) for x in out] == [
        ("restart", None),
        ("unfinished", "fitter.1.mcap"),
        ("damaged", "fitter.2.mcap"),
        ("no-stop", "fitter.3.mcap"),
        ("incomplete-segment", "fitter.3.mcap"),
        ("unreadable", "fitter.4.mcap"),
        ("disk-full", "fitter.5.mcap"),
        ("orphaned", "fitter.mcap"),
        ("restored", "fitter.mcap"),
    ]
    assert out[0]["message"] == f"fitter ran 6 times (recordings {', '.join(f['file'] for f in files)})"
    assert out[1]["message"] == "fitter.1.mcap was not closed (process killed?): salvaged 7 records; no footer"
    assert out[6]["message"] == "fitter.5.mcap: stopped: disk full (not closed: salvaged 10 records; no footer)"
    assert "fit segment 5 has a header but no payload" in out[4]["message"]


def test_the_run_stages_unfinished_windows_shortened_and_the_journal(tmp_path):
    (tmp_path / "launcher.jsonl").write_text(json.dumps({"kind": "interrupted", "message": "Ctrl-C"}) + "\n")
    stages = {
        "tdi_builder": {"files": [summary("tdi_builder.mcap")], "restarts": 0, "outputs": {"tdi": {"missing": []}}},
        "fitter": {
            "files": [summary("fitter.mcap", completed=False)],
            "restarts": 0,
            "outputs": {"fit": {"missing": [[4, 5], [8, 8]]}},
        },
        "monitor": {
            "files": [summary("monitor.mcap", completed=True)],  # its complete event: the misses were given up
            "restarts": 0,
            "outputs": {"monitor": {"missing": [[2, 2]]}},
        },
    }
    errors = [
        {"kind": "window-shortened", "stage": "fitter", "file": "fitter.mcap", "message": "window of 20 segments"},
        {"kind": "rejected", "stage": "fitter", "file": "fitter.mcap", "message": "bad"},
    ]
    out = interruptions(tmp_path, stages, {}, errors, {"segments_total": 10})
    assert [(x["stage"], x["kind"]) for x in out] == [
        ("fitter", "window-shortened"),
        ("fitter", "unfinished"),
        ("launcher", "interrupted"),
    ]
    assert out[1]["message"] == "fitter did not finish: segment(s) 4-5,8 of 10 not handled"
    assert [x["kind"] for x in interruptions(tmp_path, stages, {}, [], None)] == ["interrupted"]
