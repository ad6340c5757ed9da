"""The stage processes of a ``ttl run``: started, restarted when they die (up to
``restart`` times each), stopped at the end.

Each stage is ``python -m stages.<name> --config <run>/<name>.config.json``, its output
appended to ``<run>/<name>.log``; it receives SIGTERM when the launcher dies (it then closes
its recording and says it was orphaned).  Each runs in a process group of its own: a Ctrl-C
in the terminal reaches the launcher alone, which passes it on.  See :mod:`streamer.launch.launcher`,
"Supervision".
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ..bus.keys import control_key
from ..bus.session import Bus
from ..bus.topology import stage_module
from ..runtime.processes import start_child
from .launch_plan import RunOptions
from .run_router import exit_description

# the logger of these lines before the launcher was split into parts: log lines unchanged
log = logging.getLogger("streamer.launch.launcher")

#: What a stage's exit status says (:mod:`streamer.runtime.stage`: 3 orphaned, 4 disk full).
EXIT_MEANING = {3: ": orphaned", 4: ": disk full"}


@dataclass
class Child:
    """One stage process of the run, over its restarts."""

    name: str
    config: Path
    log: Path
    proc: subprocess.Popen | None = None
    starts: int = 0
    exit_codes: list = field(default_factory=list)
    pids: set = field(default_factory=set)
    pids_order: list = field(default_factory=list)


class Supervisor:
    """Starts, restarts and stops the stage processes (:attr:`children`).

    Parameters
    ----------
    opts : RunOptions
        ``python``, ``log_level``, ``restart``, ``stop_timeout``, ``run_id``.
    say, journal : callable
        The launcher's console line and journal record.
    """

    def __init__(self, opts: RunOptions, say, journal):
        self.opts = opts
        self.say = say
        self.journal = journal
        self.children: dict[str, Child] = {}

    def add(self, name: str, config: Path, log_path: Path) -> None:
        """A stage to run, with its configuration file and its log; started at once."""
        self.children[name] = Child(name, config, log_path)
        self.start(name)

    def start(self, name: str) -> subprocess.Popen:
        """Start stage ``name`` (again); returns its process."""
        child = self.children[name]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if name == "monitor":  # small linear algebra: threaded BLAS only fights the other stages for the cores
            env.setdefault("OPENBLAS_NUM_THREADS", "1")
        with open(child.log, "ab") as logf:
            logf.write(f"--- start {child.starts + 1} of {name} at {time.ctime()} ---\n".encode())
            logf.flush()
            cmd = [self.opts.python, "-m", stage_module(name), "--config", str(child.config)]
            # SIGTERM when the launcher dies, even while importing or opening its session (the
            # stage then closes its recording, saying it was orphaned); the terminal's Ctrl-C
            # the launcher passes on (stop_all) once it has recorded the interrupt
            proc = child.proc = start_child([*cmd, "--log-level", self.opts.log_level], logf, env, signal.SIGTERM)
        child.starts += 1
        child.pids.add(proc.pid)
        child.pids_order.append(proc.pid)
        log.info("started %s (pid %d)", name, proc.pid)
        return proc

    def last_log_line(self, name: str) -> str:
        try:
            lines = [ln for ln in self.children[name].log.read_text(errors="replace").splitlines() if ln.strip()]
        except OSError:
            return ""
        return lines[-1] if lines else ""

    def supervise(self) -> str | None:
        """Handle stages that exited; returns a reason to abort, or None."""
        for name, child in self.children.items():
            if child.proc is None or child.proc.poll() is None:
                continue
            code = child.proc.returncode
            child.exit_codes.append(code)
            child.proc = None
            how = exit_description(code)
            if code >= 0:
                how += EXIT_MEANING.get(code, "")
            self.say(f"stage {name} died ({how}); log {child.log}: {self.last_log_line(name)}")
            self.journal(
                "stage-died",
                f"stage {name} (pid {child.pids_order[-1]}) died ({how})",
                stage=name,
                pid=child.pids_order[-1],
                how=how,
                code=code,
            )
            if child.starts <= self.opts.restart:
                self.say(f"restarting {name} ({child.starts}/{self.opts.restart})")
                proc = self.start(name)
                self.journal(
                    "stage-restarted",
                    f"stage {name} restarted (pid {proc.pid})",
                    stage=name,
                    pid=proc.pid,
                    start=child.starts,
                )
            else:
                return f"stage {name} died ({how})"
        return None

    def _running(self) -> list[tuple[Child, subprocess.Popen]]:
        """The stages whose process is running, with it."""
        return [(c, c.proc) for c in self.children.values() if c.proc is not None and c.proc.poll() is None]

    def _send_stop(self, bus: Bus) -> None:
        """The run's stop message to every stage (logged when the session is closed)."""
        try:
            bus.session.put(
                control_key(self.opts.run_id, "stop"), b"{}", congestion_control=zenoh.CongestionControl.BLOCK
            )
        except Exception as exc:  # session closed
            log.warning("could not send stop: %s", exc)

    def stop_all(self, bus: Bus, first: signal.Signals | None = None) -> None:
        """Ask every stage to stop (``first``, e.g. the SIGINT of a Ctrl-C, passed on to every
        stage running, and the stop message), wait, then terminate and kill what is left."""
        if first is not None:
            for _, proc in self._running():
                proc.send_signal(first)
        self._send_stop(bus)
        deadline = time.monotonic() + self.opts.stop_timeout
        # the stop message, then SIGTERM with 15 s more, then SIGKILL with 10 s more
        for sig, wait in ((None, 0.0), (signal.SIGTERM, 15.0), (signal.SIGKILL, 10.0)):
            running = self._running()
            if not running:
                break
            if sig is not None:
                for c, proc in running:
                    self.say(f"stage {c.name} did not stop: sending {sig.name}")
                    proc.send_signal(sig)
                deadline = time.monotonic() + wait
            _wait_all(running, deadline)
        for c in self.children.values():
            if c.proc is not None:
                c.exit_codes.append(c.proc.returncode)
                c.proc = None


def _wait_all(running: list[tuple[Child, subprocess.Popen]], deadline: float) -> None:
    """Wait for the processes of ``running`` to end, until ``deadline`` (monotonic [s]; at
    least 0.1 s each)."""
    for _, proc in running:
        try:
            proc.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
