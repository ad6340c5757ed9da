"""A stage's life: signals, the launcher it depends on, and the full disk it stops on.

* Signals: SIGINT and SIGTERM are noted by :class:`streamer.runtime.processes.SignalFlag` (the
  handler stores the signal number and nothing else: no lock, no logging), polled by the
  stage's loop.
* The launcher: a stage started by ``ttl run`` dies with it (``PR_SET_PDEATHSIG``,
  :func:`die_with_launcher`) and also stops when its parent is no longer the launcher or the
  launcher's liveliness token has been gone ``orphan_grace`` seconds (:class:`LauncherWatch`;
  exit status 3).
* A stage still busy :data:`ORPHAN_EXIT_AFTER` seconds after it lost its launcher (a
  computation that does not look at the stop: a window refit on a loaded machine) exits at
  once (:class:`OrphanWatchdog`), its recording left unclosed (salvageable): nothing of a
  killed run outlives it by more than that.
* A full disk (:func:`disk_full`) stops the stage with exit status 4.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
import threading
import time

from .processes import SignalFlag, set_parent_death_signal

#: Name of the launcher's liveliness token (``ttl/<run>/alive/launcher``).
LAUNCHER = "launcher"


class StageStopping(Exception):
    """Raised inside a segment's processing by a stage told to stop (its launcher gone, a
    signal): the segment is left unhandled, for its successor (not a failure)."""


def disk_full(exc: BaseException) -> bool:
    """True for the error of a write to a full disk (or a full quota)."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def install_signal_flag() -> SignalFlag:
    """SIGINT and SIGTERM noted by a flag from now on (:class:`streamer.runtime.processes.SignalFlag`);
    ``flag.restore()`` puts the previous handlers back."""
    return SignalFlag().install()


def die_with_launcher() -> None:
    """SIGTERM to this process when the launcher (its parent) dies, so the stage closes its
    recording at once (:meth:`streamer.runtime.stage.Stage.run` then says "orphaned"); a launcher
    already gone is noticed by :meth:`LauncherWatch.orphaned` on the first turn of the loop."""
    set_parent_death_signal(signal.SIGTERM)


class LauncherWatch:
    """Whether a stage has lost the launcher that started it.

    Parameters
    ----------
    launcher_pid : int or None
        Process id of the launcher that started the stage (None: not started by one).
    orphan_grace : float
        Once the launcher's liveliness token has been seen, the stage is orphaned when it has
        been gone this long [s] (a launcher on another host).
    """

    #: Seconds between two checks in :meth:`check` [s].
    CHECK_EVERY = 0.5

    def __init__(self, launcher_pid: int | None, orphan_grace: float):
        self.launcher_pid = launcher_pid
        self.orphan_grace = orphan_grace
        self._seen = False
        self._gone_at: float | None = None
        self._checked = 0.0

    def token(self, alive: bool) -> None:
        """The launcher's liveliness token appeared (``alive``) or went (Zenoh thread)."""
        if alive:
            self._seen, self._gone_at = True, None
        elif self._seen:
            self._gone_at = time.monotonic()

    def orphaned(self) -> str | None:
        """Why the stage has lost its launcher, or None: its parent process is no longer the
        launcher that started it, or the launcher's liveliness token has been gone for
        ``orphan_grace`` seconds."""
        pid = self.launcher_pid
        if pid is not None and os.getppid() != pid:
            return f"the launcher (pid {pid}) is gone"
        gone = self._gone_at
        if gone is not None and time.monotonic() - gone >= self.orphan_grace:
            return f"the launcher's liveliness token has been gone for {self.orphan_grace:g} s"
        return None

    def check(self) -> str | None:
        """:meth:`orphaned`, at most every :attr:`CHECK_EVERY` seconds (None in between)."""
        now = time.monotonic()
        if now - self._checked < self.CHECK_EVERY:
            return None
        self._checked = now
        return self.orphaned()

    def orphaned_by_signal(self, signalled: bool, wait: float = 2.0) -> str | None:
        """:meth:`orphaned`, after a signal that may be the launcher's death (die-with-parent).

        Linux sends that signal when the launcher's thread that started this process exits;
        the other threads of a killed launcher may still be going, and this process is
        reparented only once the last has: ``getppid()`` is then still the launcher's pid
        for a moment.  So a signal with the launcher seemingly alive is given ``wait``
        seconds to show whether the launcher is going.
        """
        why = self.orphaned()
        if why or not signalled or self.launcher_pid is None:
            return why
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            time.sleep(0.05)
            if os.getppid() != self.launcher_pid:
                return self.orphaned()
        return None


#: Seconds a stage that has lost its launcher may go on computing before it exits without
#: closing (:class:`OrphanWatchdog`).  The chaos test's fitter, in a window refit of a new
#: model when its launcher was killed at load 13, was still busy 60 s later (an orphan).
ORPHAN_EXIT_AFTER = 30.0


class OrphanWatchdog:
    """A thread that ends the process (exit status 3, ``os._exit``) when the stage has lost
    its launcher (:meth:`LauncherWatch.orphaned`) and is still running ``after`` seconds
    later.  The stage's loop notices the loss itself between two segments and stops cleanly;
    this is for a segment whose processing does not return in time.  :meth:`disarm` once the
    stage is stopping (its teardown closes the recording).  Only the stage's log says why:
    the recording, written by the busy thread, is left as it is (salvaged when read)."""

    def __init__(
        self, watch: LauncherWatch, log: logging.Logger | logging.LoggerAdapter, after: float = ORPHAN_EXIT_AFTER
    ):
        self.watch, self.log, self.after = watch, log, float(after)
        self._disarmed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="orphan-watchdog", daemon=True)

    def start(self) -> OrphanWatchdog:
        if self.watch.launcher_pid is not None:
            self._thread.start()
        return self

    def disarm(self) -> None:
        self._disarmed.set()

    def _run(self) -> None:
        since = None
        while not self._disarmed.wait(1.0):
            if since is None:
                since = time.monotonic() if self.watch.orphaned() else None
            elif time.monotonic() >= since + self.after and not self._disarmed.is_set():
                self.log.error(
                    "the launcher is gone and the stage is still busy %.0f s later: exiting now "
                    "(exit status 3; the recording is left unclosed, salvaged when read)",
                    self.after,
                )
                os._exit(3)
