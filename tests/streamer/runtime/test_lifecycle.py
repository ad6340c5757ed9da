"""Unit tests of :mod:`streamer.runtime.lifecycle`: signals, the launcher a stage depends on, a
full disk (this process and its real parent; no bus)."""

import errno
import os
import signal
import time

from streamer.runtime.lifecycle import LauncherWatch, disk_full, install_signal_flag


def test_disk_full():
    assert disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert disk_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    assert not disk_full(OSError(errno.EACCES, "Permission denied"))
    assert not disk_full(ValueError("no"))


def test_sigterm_is_noted_by_the_flag_and_the_handler_restored():
    before = signal.getsignal(signal.SIGTERM)
    flag = install_signal_flag()
    try:
        assert not flag
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100):  # delivered between two bytecodes of the main thread
            if flag:
                break
            time.sleep(0.01)
        assert flag.name == "SIGTERM"
    finally:
        flag.restore()
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_stage_of_its_launcher_is_not_orphaned():
    watch = LauncherWatch(os.getppid(), orphan_grace=60.0)
    assert watch.orphaned() is None
    assert watch.orphaned_by_signal(True, wait=0.1) is None  # the parent stays: a signal of its own
    assert LauncherWatch(None, orphan_grace=60.0).orphaned() is None


def test_a_parent_that_is_not_the_launcher_is_an_orphan():
    watch = LauncherWatch(os.getppid() + 100000, orphan_grace=60.0)
    assert watch.orphaned() == f"the launcher (pid {os.getppid() + 100000}) is gone"
    assert watch.check() is not None and watch.check() is None  # checked at most every CHECK_EVERY


def test_the_launchers_token_gone_for_the_grace():
    watch = LauncherWatch(None, orphan_grace=0.2)
    watch.token(False)  # gone before it was ever seen: nothing to go by
    time.sleep(0.25)
    assert watch.orphaned() is None
    watch.token(True)
    watch.token(False)
    assert watch.orphaned() is None
    time.sleep(0.25)
    assert watch.orphaned() == "the launcher's liveliness token has been gone for 0.2 s"
    watch.token(True)  # back (a launcher on another host, reconnected)
    assert watch.orphaned() is None


#: A stand-in stage: its launcher is its parent; it arms the watchdog (``after`` 2 s) and then
#: computes without ever looking at a stop, as a window refit does, for ``busy`` seconds.
_BUSY_STAGE = """
import logging, os, sys, time
from streamer.runtime.lifecycle import LauncherWatch, OrphanWatchdog
logging.basicConfig(level=logging.INFO)
OrphanWatchdog(LauncherWatch(os.getppid(), 10.0), logging.getLogger("stage"), after=2.0).start()
print(os.getpid(), flush=True)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    sum(range(10000))
sys.exit(0)
"""

#: A stand-in launcher: starts the stage (its stderr to a file) and waits for it.
_LAUNCHER = """
import subprocess, sys
with open(sys.argv[2], "w") as err:
    sys.exit(subprocess.run([sys.executable, "-c", sys.argv[1], sys.argv[3]], stderr=err).returncode)
"""


def _launch(tmp_path, busy: float):
    import subprocess
    import sys

    err = tmp_path / "stage.err"
    launcher = subprocess.Popen(
        [sys.executable, "-c", _LAUNCHER, _BUSY_STAGE, str(err), str(busy)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    stage_pid = int(launcher.stdout.readline())
    return launcher, stage_pid, err


def test_a_stage_still_busy_after_its_launcher_died_exits(tmp_path):
    """A stage whose launcher is SIGKILLed while it computes exits ``after`` seconds later
    (the chaos test's fitter, in a window refit at load 13, was still running 60 s after its
    launcher's death), saying why in its log."""
    import psutil

    launcher, stage_pid, err = _launch(tmp_path, busy=120.0)
    stage = psutil.Process(stage_pid)
    launcher.kill()
    launcher.wait(10)
    t = time.monotonic()
    gone, alive = psutil.wait_procs([stage], timeout=20)
    for p in alive:
        p.kill()
    assert gone and not alive, "the orphaned stage kept computing"
    assert time.monotonic() - t >= 1.0  # not before its grace: the watchdog, not the signal
    assert "the launcher is gone and the stage is still busy 2 s later: exiting now" in err.read_text()


def test_a_busy_stage_with_its_launcher_alive_is_left_alone(tmp_path):
    """The watchdog does nothing while the launcher lives: a stage computing 5 s (more than
    the 2-s grace) ends by itself, exit status 0."""
    launcher, _, err = _launch(tmp_path, busy=5.0)
    assert launcher.wait(60) == 0, err.read_text()
    assert "exiting now" not in err.read_text()
