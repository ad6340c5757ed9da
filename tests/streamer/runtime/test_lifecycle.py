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
