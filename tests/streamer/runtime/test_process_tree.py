"""Signals and dead parents: the router stops on SIGTERM whenever it comes, and a killed
``ttl run`` leaves no process behind (router, stages, the replayer's planning check), on
loopback, within bounded time."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
from proc_testutil import ChildProcesses, output, wait_for
from ttl_testutil import run_args

from streamer.bus.session import free_port
from streamer.recording.recorder import read_recording
from streamer.runtime.processes import SignalFlag

ROOT = Path(__file__).resolve().parents[3]


def ttl(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from streamer.tools.cli import main; sys.exit(main())", *args]


def descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def cmdlines(procs) -> list[str]:
    out = []
    for p in procs:
        try:
            out.append(" ".join(p.cmdline()))
        except psutil.Error:
            pass
    return out


def test_signal_flag_handler_takes_no_lock():
    """The handler of SignalFlag only stores the number: it returns even while every lock
    the main thread could hold is held (a threading.Event's handler would block here)."""
    flag = SignalFlag((signal.SIGUSR1,)).install()
    try:
        event = threading.Event()
        with event._cond:  # what Event.wait() holds when a signal lands inside it
            os.kill(os.getpid(), signal.SIGUSR1)
            time.sleep(0.05)  # the handler runs here, in this thread, lock held
            assert flag and flag.name == "SIGUSR1"
        assert flag.wait(0.1)
    finally:
        flag.restore()


def test_router_stops_on_sigterm_at_any_moment(tmp_path):
    """SIGTERM at random moments of the router's wait loop: it closes and exits 0 each time
    (its handler called threading.Event.set() and could deadlock on the Event's lock)."""
    children = ChildProcesses(tmp_path)
    try:
        rng = random.Random(5)
        for attempt in range(3):
            port = free_port()
            proc = children.start(
                ttl("router", "--insecure", "--listen", f"tcp/127.0.0.1:{port}"), f"router{attempt}", cwd=ROOT
            )
            wait_for(
                lambda proc=proc: "listening on" in output(proc) or proc.poll() is not None, 60, "the router to listen"
            )
            assert proc.poll() is None, output(proc)
            time.sleep(rng.uniform(0.0, 1.0))  # anywhere in the 0.5-s wait cycle
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(15) == 0, output(proc)
            assert "SIGTERM: closing" in output(proc)
    finally:
        children.close()


def test_tied_child_dies_with_its_parent(tmp_path):
    """tied_to_parent: the child of a SIGKILLed parent gets its signal; a child whose parent
    died before prctl exits at once instead of running on."""
    code = (
        f"import subprocess, sys, time, signal; sys.path.insert(0, {str(ROOT)!r}); "
        "from streamer.runtime.processes import tied_to_parent; "
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'], "
        "preexec_fn=tied_to_parent(signal.SIGKILL)); print(p.pid, flush=True); time.sleep(120)"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        child = psutil.Process(int(parent.stdout.readline()))
        parent.kill()
        parent.wait(10)
        gone, alive = psutil.wait_procs([child], timeout=10)
        assert not alive, "the child outlived its SIGKILLed parent"
    finally:
        for p in (parent,):
            if p.poll() is None:
                p.kill()


@pytest.mark.parametrize("when", ["planning", "running"])
def test_killed_launcher_leaves_nothing_alive(when, tmp_path):
    """SIGKILL of ``ttl run`` while the replayer checks the plan, or once the router and the
    stages run: every descendant is gone within 30 s (die-with-parent: the router and the
    check by SIGKILL, the stages by SIGTERM, closing their recordings)."""
    children = ChildProcesses(tmp_path)
    port = free_port()
    # a long simulation makes the planning check last; the run itself never gets far
    sim = "--duration 30d --orbit equal --seed 1" if when == "planning" else "--duration 2h --orbit equal --seed 1"
    proc = children.start(
        ttl(
            *run_args(
                f"kill-{when}",
                tmp_path / "rec",
                "--insecure",
                "--listen",
                f"tcp/127.0.0.1:{port}",
                sim=sim,
                timeout=300,
            )
        ),
        "ttl-run",
        cwd=ROOT,
    )
    everything: list[psutil.Process] = []
    try:

        def ready():
            if proc.poll() is not None:
                return True
            lines = cmdlines(descendants(proc.pid))
            if when == "planning":
                return any("--check" in c for c in lines)
            # every stage has opened its session and its recording
            return any(" router" in c for c in lines) and len(list(run_dir.glob("*.mcap"))) >= 4

        run_dir = tmp_path / "rec" / f"kill-{when}"
        wait_for(ready, 120, f"ttl run {when}")
        assert proc.poll() is None, output(proc)
        if when == "planning":
            time.sleep(1.0)  # the check is under way (importing, simulating)
        everything = descendants(proc.pid)
        assert everything, output(proc)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        t = time.monotonic()
        gone, alive = psutil.wait_procs(everything, timeout=30)
        assert not alive, f"left running after ttl run was killed: {cmdlines(alive)}"
        print(f"{len(gone)} descendants of the killed ttl run gone in {time.monotonic() - t:.1f} s")
        for path in sorted(run_dir.glob("*.mcap")):  # each stage closed its recording, saying why
            rec = read_recording(path)
            stop = [e for e in rec.json("events") if e["kind"] == "stop"]
            assert rec.complete and stop and stop[-1]["details"]["orphaned"], (path.name, rec.problem, stop)
    finally:  # whatever the outcome, nothing of this test runs on (a 30-day simulation would)
        for p in everything + descendants(proc.pid):
            try:
                p.kill()
            except psutil.Error:
                pass
        children.close()
