"""Helpers every process test shares: child processes that do not outlive the test, their
output, polling.  Imported by name (``tests/`` is on pytest's ``pythonpath``, pyproject.toml)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest


class ChildProcesses:
    """Child processes of a test, each in a session of its own, its output in a file of
    ``tmp_path``; all killed (with their children) at the end."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []

    def start(self, cmd: list[str], name: str, env: dict | None = None, cwd=None) -> subprocess.Popen:
        """Start ``cmd``, output to ``<tmp_path>/<name>.out`` (:func:`output`)."""
        path = self.tmp_path / f"{name}.out"
        env = dict(os.environ if env is None else env, PYTHONUNBUFFERED="1")
        with open(path, "wb") as log:
            proc = subprocess.Popen(
                cmd,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                cwd=self.tmp_path if cwd is None else cwd,
                start_new_session=True,
            )
        proc.out_path = path
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait(10)


def output(proc) -> str:
    """What a child started by :class:`ChildProcesses` wrote so far."""
    return Path(proc.out_path).read_text(errors="replace")


def wait_for(predicate, timeout: float, what: str, interval: float = 0.05):
    """Poll ``predicate`` until it returns something true; fail naming ``what`` on timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout} s waiting for {what}")


def finish(proc, timeout: float) -> int:
    """Wait for ``proc``; fail with its output when it runs too long."""
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{proc.args} still running after {timeout} s:\n{output(proc)[-4000:]}")
