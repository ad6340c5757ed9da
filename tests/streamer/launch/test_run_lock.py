"""One launcher per run directory (``streamer.launch.run_journal.lock_run``): two ``ttl run`` with
one ``--run-id`` and ``--recordings`` used to both run, share ``board.json`` and the logs,
and leave ``ttl inspect`` reporting a killed launcher that was not killed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from streamer.launch.launch_plan import LaunchError
from streamer.launch.run_journal import lock_run

ROOT = Path(__file__).resolve().parents[3]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def test_a_held_run_is_refused_and_released_with_its_holder(tmp_path):
    held = lock_run(tmp_path)
    with pytest.raises(LaunchError, match=rf"in use: its launcher \(ttl run pid {os.getpid()}\)"):
        lock_run(tmp_path)
    held.close()
    lock_run(tmp_path).close()


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    """The kernel drops the lock with the process, however it ends (here SIGKILL): a
    ``--resume`` after a killed launcher takes the run again."""
    code = f"from streamer.launch.run_journal import lock_run; f = lock_run(__import__('pathlib').Path({str(tmp_path)!r})); print('held', flush=True); __import__('time').sleep(60)"
    p = subprocess.Popen([sys.executable, "-c", code], env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        with pytest.raises(LaunchError, match=f"pid {p.pid}"):
            lock_run(tmp_path)
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait()
    lock_run(tmp_path).close()


# two whole `ttl run`s (38 s): behind the ops marker, to keep `make test` near its 10-min budget (CI 2026-11-28: 812 s)
@pytest.mark.ops
def test_a_second_ttl_run_of_a_running_run_is_refused(tmp_path):
    """Two real launchers: the second ends at once with one error line, exit status 2, and
    writes nothing into the first one's directory (its journal holds one start)."""
    args = ["--run-id", "r1", "--recordings", "rec", "--segment", "10min", "--insecure"]
    first = subprocess.Popen(
        [sys.executable, "-m", "streamer.tools.main", "run", "--simulate", "--duration 2h", *args, "--quiet"],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    journal = tmp_path / "rec" / "r1" / "launcher.jsonl"
    try:
        deadline = time.monotonic() + 120
        while not (journal.exists() and '"start"' in journal.read_text()) and time.monotonic() < deadline:
            assert first.poll() is None, first.stderr.read().decode()
            time.sleep(0.2)
        second = subprocess.run(
            [sys.executable, "-m", "streamer.tools.main", "run", "--simulate", "--duration 2h", *args, "--quiet"],
            cwd=tmp_path,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=120,
        )
        # the plan's line ("replay: 12 segments ...", which ``--quiet`` keeps), then the error
        errors = [x for x in second.stderr.strip().splitlines() if x.startswith("ttl run: error:")]
        assert second.returncode == 2 and len(errors) == 1 and "Traceback" not in second.stderr, second.stderr
        assert errors[0].startswith("ttl run: error: run r1 is in use") and f"pid {first.pid}" in errors[0], errors
        starts = [json.loads(x) for x in journal.read_text().splitlines() if '"start"' in x]
        assert len(starts) == 1 and first.poll() is None
    finally:
        os.killpg(first.pid, signal.SIGINT)
        first.wait(timeout=120)
