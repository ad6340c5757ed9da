"""Unit tests of :mod:`streamer.tools.inspect_records`: what ``ttl inspect`` reads besides the MCAP
files (the launcher's journal, the router's refusals, the plan), from files on disk."""

import json

import pytest

from streamer.tools.inspect_records import (
    MAX_REFUSALS,
    InspectError,
    json_object,
    launcher_journal,
    read_plan,
    run_gaps,
    security_report,
)


def lines(*records) -> str:
    return "".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in records)


def test_the_launcher_journal_lists_every_interruption(tmp_path):
    (tmp_path / "launcher.jsonl").write_text(
        lines(
            {"kind": "start", "launcher_pid": 11, "time": 1.0},
            {"kind": "stage-died", "stage": "fitter", "time": 2.0, "message": "fitter died (exit -9)"},
            {"kind": "stage-restarted", "stage": "fitter", "time": 3.0, "message": "restarted"},
            {"kind": "progress", "time": 3.5},  # bookkeeping: not an interruption
            {"kind": "start", "launcher_pid": 12, "time": 4.0},  # the first launcher never ended
            {"kind": "resume", "time": 4.0, "message": "resumed"},
            {"kind": "end", "time": 5.0},
            '{"kind": "start", "launcher_pid"',  # cut off
            [1, 2],
            {"kind": "start", "launcher_pid": 13, "time": 6.0},
        )
    )
    out = launcher_journal(tmp_path)
    assert [(r["stage"], r["kind"]) for r in out] == [
        ("fitter", "stage-died"),
        ("fitter", "stage-restarted"),
        ("launcher", "launcher-killed"),
        ("launcher", "resume"),
        ("launcher", "journal-unreadable"),
        ("launcher", "launcher-killed"),
    ]
    assert out[2]["time"] == 1.0 and "pid 11" in out[2]["message"] and "without its end" in out[2]["message"]
    assert "line 8 is not JSON" in out[4]["message"]
    assert "pid 13" in out[5]["message"] and "still running" in out[5]["message"]
    assert launcher_journal(tmp_path / "absent") == []


def test_the_security_report_counts_refusals_by_kind(tmp_path):
    assert security_report(tmp_path) == {
        "file": str(tmp_path / "security.jsonl"),
        "present": False,
        "count": 0,
        "kinds": {},
        "unreadable": [],
    }
    refused = [{"kind": "acl-denied", "key": f"ttl/r1/fit/{i}"} for i in range(MAX_REFUSALS + 2)]
    (tmp_path / "security.jsonl").write_text(
        lines(*refused, {"kind": "tls-refused", "peer": "x"}, "garbage", {"no": "kind"}, "")
    )
    report = security_report(tmp_path)
    assert report["present"] and report["count"] == MAX_REFUSALS + 3
    assert report["kinds"]["acl-denied"]["count"] == MAX_REFUSALS + 2
    assert report["kinds"]["acl-denied"]["first"] == refused[:MAX_REFUSALS]
    assert report["kinds"]["tls-refused"]["count"] == 1
    assert report["unreadable"] == [MAX_REFUSALS + 4, MAX_REFUSALS + 5]


def test_an_unreadable_security_file_names_it(tmp_path):
    (tmp_path / "security.jsonl").mkdir()  # there, but not a file
    with pytest.raises(InspectError, match="security.jsonl: cannot read"):
        security_report(tmp_path)


def test_plan_gaps_and_json_objects(tmp_path):
    assert read_plan(tmp_path) is None
    (tmp_path / "plan.json").write_text("{broken")
    assert read_plan(tmp_path) is None
    (tmp_path / "plan.json").write_text(json.dumps({"fs": 4.0, "segments": 3}))
    assert read_plan(tmp_path) == {"fs": 4.0, "segments": 3}
    errors = [
        {"kind": "gap", "stage": "tdi_builder", "index": 2, "message": "segment 2 never came"},
        {"kind": "rejected", "stage": "fitter", "index": 1, "message": "bad"},
    ]
    assert run_gaps({}, errors, None) == [
        {"stage": "tdi_builder", "kind": "missing", "index": 2, "message": "segment 2 never came"}
    ]
    assert json_object({"a": 1}) == {"a": 1} and json_object([1]) == {} and json_object(None) == {}
