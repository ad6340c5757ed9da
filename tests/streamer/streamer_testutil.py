"""Helpers of the streamer tests: child processes running tests/streamer/procs.py, polling."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROCS = Path(__file__).with_name("procs.py")
if str(ROOT) not in sys.path:  # `streamer` may not be in the editable install's mapping yet
    sys.path.insert(0, str(ROOT))


class Children:
    """Starts child processes and makes sure none outlives the test."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []

    def start(self, role: str, **args) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
        log = open(self.tmp_path / f"{role}-{len(self.procs)}.log", "wb")
        cmd = [sys.executable, str(PROCS), role, json.dumps(args)]
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        proc.log_path = Path(log.name)
        log.close()
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)


def output_of(proc) -> str:
    return Path(proc.log_path).read_text(errors="replace")


def wait_for(predicate, timeout: float, what: str, interval: float = 0.05):
    """Poll ``predicate`` until true; fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout} s waiting for {what}")
