"""A monitor restarted after its inputs left every cache (``make test-ops``; marker ``ops``):
a real ``ttl run`` on a loopback Zenoh, its MCAP files read back (issue 33).

The chaos test with model changes never ended when the monitor restarted after the caches had
moved on: it waited for segments no cache held, as long as their producers lived.  Here that
is made to happen on purpose rather than by a lucky draw: the monitor is stopped (SIGSTOP)
after its first segment, the fitter is killed (restarted by the launcher: its new process's
cache holds none of the fits its earlier process published) and goes on as far as the
replayer's window lets it, then the stopped monitor is killed.  The restarted monitor must take the fits of the fitter's earlier
process from its recordings (:mod:`streamer.runtime.catch_up`, a ``recovered`` event) and the run
must end with exit status 0 and every segment drawn.
"""

from __future__ import annotations

import json
import signal

import pytest
from ttl_testutil import MONITOR, Procs, finish, output, stage_processes, wait_for

from streamer.bus.session import Bus, SessionSettings, free_port
from streamer.recording.recorder import read_recording

pytestmark = [pytest.mark.ops, pytest.mark.skipif(not MONITOR, reason="no monitor stage")]

SEGMENTS = 6


def _handled(board: dict, stage: str) -> set[int]:
    msg = board.get(stage) or {}
    return {i for key in ("done", "failed") for a, b in msg.get(key, ()) for i in range(a, b + 1)}


def test_a_monitor_restarted_after_the_fitter_takes_the_fits_no_cache_holds_from_the_recordings(tmp_path):
    port = free_port()
    procs = Procs(tmp_path)
    run = "late-monitor"
    rec = tmp_path / "rec"
    stopped = None
    try:
        proc = procs.ttl(
            "run", "--simulate", f"--duration {SEGMENTS}h --orbit unequal --seed 1", "--segment", "1h",
            "--run-id", run, "--recordings", str(rec), "--timeout", "400", "--insecure",
            "--listen", f"tcp/127.0.0.1:{port}", "--restart", "2",
        )  # fmt: skip
        with Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as bus:
            board: dict = {}

            def on_sample(sample):
                msg = json.loads(sample.payload.to_bytes())
                board[msg["stage"]] = msg

            bus.segment_subscriber(f"ttl/{run}/control/board/*", on_sample, history=1)
            wait_for(lambda: _handled(board, "monitor") or proc.poll() is not None, 300, "the monitor's first segment")
            stopped = stage_processes(proc)["monitor"]
            stopped.send_signal(signal.SIGSTOP)
            first = _handled(board, "monitor")
            wait_for(lambda: len(_handled(board, "fitter")) >= 3 or proc.poll() is not None, 300, "fitter at 3")
            fitter = stage_processes(proc)["fitter"]
            fitter.send_signal(signal.SIGKILL)
            # the restarted fitter goes on to segment 4 (the replayer stays within 4 segments of
            # the stopped monitor); its cache holds only what it published
            wait_for(
                lambda: len(_handled(board, "fitter")) >= 5 or proc.poll() is not None,
                300,
                "the restarted fitter at segment 4",
            )
            assert proc.poll() is None, output(proc)[-3000:]
            stopped.send_signal(signal.SIGKILL)  # the launcher restarts it
            code = finish(proc, 600)
        out = output(proc)
    finally:
        if stopped is not None and stopped.is_running():
            stopped.send_signal(signal.SIGCONT)
        procs.close()
    assert code == 0, out[-4000:]
    assert "stage fitter died (killed by SIGKILL)" in out and "stage monitor died (killed by SIGKILL)" in out, out
    run_dir = rec / run
    # the fits the fitter's earlier process published, in no cache when the monitor came back
    earlier = {s.header.index for s in read_recording(run_dir / "fitter.1.mcap").segments("fit")}
    needed = earlier - first
    assert needed, (earlier, first)
    monitor = read_recording(run_dir / "monitor.mcap")
    recovered = [e for e in monitor.json("events") if e.get("kind") == "recovered"]
    got = {
        i
        for e in recovered
        if e["details"]["topic"] == "fit"
        for a, b in e["details"]["indices"]
        for i in range(a, b + 1)
    }
    assert needed <= got, (needed, recovered)
    assert not [w for w in monitor.json("warnings") if w.get("kind") == "input-lost"]
    drawn = {s.header.index for path in run_dir.glob("monitor*.mcap") for s in read_recording(path).segments("monitor")}
    assert drawn == set(range(SEGMENTS)), drawn
