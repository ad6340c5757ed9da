"""A run's inputs are pinned, and its exit status says what happened (issue 33).

* The plan pins every telemetry file (size, modification time, sampled SHA-256:
  ``streamer/launch/input_pins.py``); the replayer refuses a file that is not that one, at open
  and before reading each segment, and ``ttl run --resume`` refuses it too.
* ``ttl run`` exits 3 when segments of the plan outside the gaps in the data got no fit or
  no residual, and its summary line says how many and which (``streamer/launch/run_verdict.py``).
* Ops (marker ``ops``): the telemetry file swapped for a shorter one mid-run stops the run
  with an error naming the file (it used to read segments 3-5 from the new file, report 6-11
  as gaps and exit 0 with 6/12 fits); a control payload nested 500 deep sent to every stage
  is refused, reported by ``ttl control``, and changes nothing.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from ttl_testutil import (
    STAGES,
    Procs,
    finish,
    fits_and_residuals,
    handled_count,
    output,
    run_args,
    ttl_command,
    wait_for,
    watch_board,
)

from stages.replayer import FileSource
from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.launch.input_pins import InputChanged, check_pins, check_stat, pin
from streamer.launch.launcher import Launcher, RunOptions
from streamer.launch.run_verdict import EXIT_LOST, fit_span, lost_segments
from streamer.recording.recorder import read_recording
from streamer.runtime.plan import Plan
from streamer.runtime.progress import Progress
from streamer.runtime.rangeset import RangeSet
from ttlcore.io.reader import read_telemetry


def simulate(path: Path, duration: str, seed: int = 1) -> Path:
    """``ttl simulate`` in this process (the command's own entry point, without a process
    start for each of the module's files)."""
    from ttlcore.cli.main import main

    args = [
        "simulate",
        "--duration",
        duration,
        "--orbit",
        "unequal",
        "--seed",
        str(seed),
        "--out",
        str(path),
        "--quiet",
    ]
    assert main(args) == 0
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Two hours and one hour of telemetry (seed 1), two hours of another seed."""
    d = tmp_path_factory.mktemp("telemetry")
    return {
        "2h": simulate(d / "two.h5", "2h"),
        "1h": simulate(d / "one.h5", "1h"),
        "2h-seed2": simulate(d / "two-seed2.h5", "2h", seed=2),
    }


# ---------------------------------------------------------------------------- the pins


def test_pins_name_what_changed(files, tmp_path):
    f = tmp_path / "mission.h5"
    shutil.copy2(files["2h"], f)
    planned = pin(f)
    assert planned["size"] == f.stat().st_size and planned["path"] == str(f.resolve())
    check_pins([planned], [f])  # unchanged: nothing to say
    check_stat(planned)
    # replaced by a shorter file
    shutil.copy(files["1h"], f)
    with pytest.raises(InputChanged, match=rf"{re.escape(str(f.resolve()))}: changed since the run was planned: size"):
        check_stat(planned)
    # replaced by a file of the same size, its modification time set back: the digest sees it
    shutil.copy(files["2h-seed2"], f)
    os.utime(f, ns=(planned["mtime_ns"], planned["mtime_ns"]))
    assert f.stat().st_size == planned["size"]
    check_stat(planned)  # the cheap check cannot tell
    with pytest.raises(InputChanged, match=r"content differs \(sampled SHA-256\)"):
        check_pins([planned], [f])
    # another file than the plan's
    with pytest.raises(InputChanged, match="not an input of the run as planned"):
        check_pins([planned], [files["1h"]])


def test_a_plan_carries_its_pins_and_refuses_a_bad_one(files):
    plan = FileSource([files["2h"]], 600.0).plan()
    assert [p["path"] for p in plan.inputs] == [str(files["2h"].resolve())]
    again = Plan.from_dict(json.loads(json.dumps(plan.to_dict())))
    assert again.inputs == plan.inputs
    bad = plan.to_dict()
    bad["inputs"][0]["size"] = "big"
    with pytest.raises(ValueError, match=r"plan: inputs\[0\]\.size: expected int"):
        Plan.from_dict(bad)


def test_the_replayer_refuses_a_file_changed_under_it(files, tmp_path):
    """At open (a restarted replayer) and before reading a segment (the running one)."""
    f = tmp_path / "mission.h5"
    shutil.copy2(files["2h"], f)
    source = FileSource([f], 600.0)
    planned = source.plan().inputs
    FileSource([f], 600.0, planned)  # the same file: accepted
    tm, _ = source.segment(2)
    assert tm.size == 2400
    os.replace(shutil.copy(files["1h"], tmp_path / "new.h5"), f)  # swapped, as `mv new.h5 mission.h5`
    with pytest.raises(InputChanged, match=rf"{re.escape(str(f.resolve()))}: changed since the run was planned: size"):
        source.segment(3)
    with pytest.raises(InputChanged, match="changed since the run was planned"):
        FileSource([f], 600.0, planned)


def test_resume_refuses_a_file_changed_since_the_run_was_planned(files, tmp_path):
    """``ttl run --resume`` of a run planned with another file: one line naming the file and
    what changed, exit status 2, no process started."""
    f = tmp_path / "mission.h5"
    shutil.copy2(files["2h"], f)
    run_dir = tmp_path / "rec" / "r1"
    run_dir.mkdir(parents=True)
    (run_dir / "plan.json").write_text(json.dumps(FileSource([f], 600.0).plan().to_dict()))
    time.sleep(0.01)
    shutil.copy(files["2h-seed2"], f)  # the same size, another content, a new modification time
    res = subprocess.run(
        ttl_command(
            *run_args("r1", tmp_path / "rec", "--insecure", "--resume", telemetry=f, segment="10min", timeout=None)
        ),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert f"--resume: {f.resolve()}: changed since the run was planned: modified at" in res.stderr, res.stderr
    assert "content differs" in res.stderr and "give a new --run-id" in res.stderr, res.stderr
    assert sorted(p.name for p in run_dir.iterdir()) == ["plan.json"]  # nothing started, nothing written


# ---------------------------------------------------------------------------- the exit status


def board(total: int, fits, residuals, gaps=(), stages=("replayer", "tdi_builder", "fitter", "subtractor")):
    out = {}
    for s in stages:
        p = Progress(s, segments_total=total)
        p.done.update(i for i in range(total) if i not in gaps)
        p.failed.update(gaps)
        p.gaps.update(gaps)
        out[s] = p
    out["fitter"].extra["fits"] = RangeSet(fits)
    out["subtractor"].done = RangeSet(residuals)
    out["subtractor"].failed.update(i for i in range(total) if i not in residuals)
    return out


def launcher(tmp_path, progress, errors=(), fitter=None) -> tuple[Launcher, io.StringIO]:
    out = io.StringIO()
    la = Launcher(RunOptions(run_id="r1", recordings=tmp_path, stage_options={"fitter": fitter or {}}), out=out)
    la.expected = list(progress)
    la.run_plan = {"segments_total": 12, "samples": 2400, "fs": 4.0}
    la.progress = progress
    la.errors = list(errors)
    return la, out


def test_segments_without_a_fit_make_the_run_exit_3_naming_them(tmp_path):
    """The measured case: every stage handled every segment, 6 of the 12 got a fit.  It exited 0."""
    la, out = launcher(tmp_path, board(12, range(6), range(12)))
    assert la.report(None) == EXIT_LOST == 3, out.getvalue()
    last = out.getvalue().strip().splitlines()[-1]
    assert "ended (exit status 3): 12 segments, 6 lost outside the gaps (no fit: 6..11)" in last, last


def test_gaps_in_the_data_are_not_losses(tmp_path):
    la, out = launcher(tmp_path, board(12, [0, 1, 2, 5, 6, 7, 8, 9, 10, 11], range(12), gaps=(3, 4)))
    la.progress["subtractor"].done = RangeSet(i for i in range(12) if i not in (3, 4))
    la.progress["subtractor"].failed = RangeSet([3, 4])
    assert la.report(None) == 0, out.getvalue()
    assert "done: 12 segments," in out.getvalue() and "lost" not in out.getvalue()


def test_a_missing_fit_or_residual_is_a_loss(tmp_path):
    # a fit announced but never received (the subtractor applied an older one)
    missing = {"stage": "subtractor", "kind": "missing-fit", "index": 7, "message": "fit 7 ... never arrived"}
    la, out = launcher(tmp_path, board(12, range(12), range(12)), errors=[missing])
    assert la.report(None) == 3
    assert "1 lost outside the gaps (no fit: 7)" in out.getvalue(), out.getvalue()
    # residuals given up: exit 1 (a segment given up), and the summary still says which
    la, out = launcher(tmp_path, board(12, range(12), [0, 1, 2, 3, 4, 5, 6, 7, 8, 10]))
    assert la.report(None) == 1
    assert "ended (exit status 1): 12 segments, 2 lost outside the gaps (no residual: 9, 11)" in out.getvalue()


def test_a_longer_fft_segment_fits_every_other_segment_without_loss(tmp_path):
    """``--fit-segment 20min`` on 10-min segments: a fit every second segment covers both."""
    assert fit_span({"fit_segment": "20min"}, {"samples": 2400, "fs": 4.0}) == 2
    la, out = launcher(tmp_path, board(12, range(1, 12, 2), range(12)), fitter={"fit_segment": "20min"})
    assert la.report(None) == 0, out.getvalue()
    assert lost_segments(12, ["fitter"], la.progress, span=1)["no_fit"] == list(range(0, 12, 2))


# ---------------------------------------------------------------------------- ops: live runs


@pytest.mark.ops
def test_telemetry_file_swapped_mid_run_stops_the_run(files, tmp_path):
    """The measured failure: ``mission.h5`` (2 h, 12 segments of 10 min) replaced by a 1-h file
    after segment 2.  Before: segments 3-5 read from the new file without error, 6-11 reported
    as gaps, exit 0 with 6/12 fits.  Now: the replayer stops at the first segment it would
    read from the new file (``input-changed`` error naming the file and its size), its restart
    refuses the file at open, no segment of the new file is published, ``ttl run`` exits 1,
    and ``--resume`` of the run refuses the file too."""
    f = tmp_path / "mission.h5"
    shutil.copy2(files["2h"], f)
    port = free_port()
    listen = ["--listen", f"tcp/127.0.0.1:{port}", "--insecure"]
    # --pace 150: a segment every 4 s
    args = run_args(
        "swap", tmp_path / "rec", *listen, "--pace", "150", "--restart", "1", telemetry=f, segment="10min", timeout=600
    )
    procs = Procs(tmp_path)
    try:
        proc = procs.ttl(*args)
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            seen = watch_board(bus, "swap")
            wait_for(lambda: handled_count(seen, "replayer") >= 3 or proc.poll() is not None, 600, "segment 2 replayed")
            os.replace(shutil.copy(files["1h"], tmp_path / "new.h5"), f)
            code = finish(proc, 600)
        out = output(proc)
        resumed = subprocess.run(ttl_command(*args, "--resume"), capture_output=True, text=True, timeout=300)
    finally:
        procs.close()
    name = str(f.resolve())
    assert code == 1, out[-4000:]
    assert f"input-changed: {name}: changed since the run was planned: size" in out, out[-4000:]
    assert "stage replayer died (exit status 2)" in out, out[-4000:]
    run_dir = tmp_path / "rec" / "swap"
    log = (run_dir / "replayer.log").read_text()
    assert log.count(f"ttl stage replayer: error: {name}: changed since the run was planned") == 2, log[-3000:]
    errors = [e for r in sorted(run_dir.glob("replayer*.mcap")) for e in read_recording(r).json("errors")]
    changed = [e for e in errors if e["kind"] == "input-changed"]
    assert len(changed) == 1 and changed[0]["index"] >= 3, errors
    # every telemetry segment published is the original file's
    published = {
        s.header.index: s
        for r in sorted(run_dir.glob("replayer*.mcap"))
        for s in read_recording(r).segments("telemetry")
    }
    assert sorted(published) == list(range(changed[0]["index"])), sorted(published)
    for i, s in published.items():
        want = read_telemetry(files["2h"], i * 2400, (i + 1) * 2400)
        np.testing.assert_array_equal(s.arrays["eta"], want.eta)
    assert "lost outside the gaps" in out.splitlines()[-1], out[-2000:]
    assert resumed.returncode == 2, (resumed.stdout, resumed.stderr)
    assert f"--resume: {name}: changed since the run was planned: size" in resumed.stderr, resumed.stderr


SIM = "--duration 6h --orbit unequal --seed 1"
NESTED = '{"effects": ' + "[" * 500 + "]" * 500 + "}"


@pytest.mark.ops
def test_nested_control_payload_is_refused_by_every_stage(tmp_path):
    """``ttl control <stage> model '{"effects": [[[...500 deep...]]]}'`` to every stage of a live
    run: each refuses it (the bounded parser: nested too deep), ``ttl control`` reports the
    refusal (exit status 2, naming the stage), the run ends with exit status 0 and its fits and
    residuals equal a clean run's bit for bit."""
    procs = Procs(tmp_path)
    port = free_port()
    sent = {}
    try:
        clean = procs.ttl(*run_args("clean", tmp_path / "rec", "--insecure", sim=SIM), name="clean")
        assert finish(clean, 900) == 0, output(clean)[-3000:]
        proc = procs.ttl(
            *run_args(
                "nested", tmp_path / "rec", "--insecure", "--listen", f"tcp/127.0.0.1:{port}", "--pace", "300", sim=SIM
            )
        )
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            seen = watch_board(bus, "nested")
            wait_for(lambda: handled_count(seen, "fitter") >= 1 or proc.poll() is not None, 600, "the first fit")
        for stage in STAGES:
            sent[stage] = subprocess.run(
                ttl_command(
                    "control",
                    stage,
                    "model",
                    NESTED,
                    "--run",
                    "nested",
                    "--connect",
                    f"tcp/127.0.0.1:{port}",
                    "--wait",
                    "10",
                ),
                capture_output=True,
                text=True,
                timeout=120,
            )
        code = finish(proc, 900)
        out = output(proc)
    finally:
        procs.close()
    assert code == 0, out[-4000:]
    for stage, res in sent.items():
        assert res.returncode == 2, (stage, res.stdout, res.stderr)
        assert f"{stage} rejected model" in res.stderr and "JSON nested" in res.stderr, (stage, res.stderr)
    run_dir = tmp_path / "rec" / "nested"
    for stage in STAGES:
        rec = read_recording(run_dir / f"{stage}.mcap")
        refused = [c for c in rec.json("control") if c.get("accepted") is False]
        assert len(refused) == 1 and "nested" in refused[0]["message"], (stage, rec.json("control"))
    got, ref = fits_and_residuals(run_dir), fits_and_residuals(tmp_path / "rec" / "clean")
    for topic in ("fit", "residual"):
        assert sorted(got[topic]) == sorted(ref[topic]) == list(range(6)), topic
        for i, arrays in ref[topic].items():
            for name, arr in arrays.items():
                np.testing.assert_array_equal(got[topic][i][name], arr, err_msg=f"{topic} {i} {name}")


def test_a_segment_the_fitter_had_no_data_for_yet_is_not_lost(tmp_path):
    """Its ``no-fit`` warning (in the fitter's recording) says "no FFT segment with data yet"
    (the first segments gated or gapped): not a loss; a segment the window could not fit is."""
    from streamer.recording.recorder import Recorder, stage_record

    run_dir = tmp_path / "r1"
    run_dir.mkdir()
    with Recorder(run_dir / "fitter.mcap", metadata={"run": "r1", "stage": "fitter"}) as rec:
        for i, why in (
            (0, "the window holds no FFT segment with data yet (the first ones were gaps or left out)"),
            (5, "no FFT segment completed, or the window determines no parameter"),
        ):
            rec.write_json(
                "warnings", stage_record("r1", "fitter", "no-fit", f"segment {i}: no fit published: {why}", index=i)
            )
    la, out = launcher(tmp_path, board(12, [1, 2, 3, 4, 6, 7, 8, 9, 10, 11], range(12)))
    assert la.report(None) == 3, out.getvalue()
    assert "1 lost outside the gaps (no fit: 5)" in out.getvalue(), out.getvalue()
