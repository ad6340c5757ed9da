"""Child processes of the operations layer (router, stages, viewers): tie them to their
parent, wait until they listen, stop them; and signal handling that cannot deadlock."""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import threading
import time

from ..bus.session import LOOPBACK

#: ``prctl`` option that asks for a signal when the parent dies (Linux).
PR_SET_PDEATHSIG = 1


def _find_prctl():
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux
        return None


# Looked up once, in the parent: a child forked from a process with threads (Zenoh's) should
# not have to dlopen between fork and exec.
_PRCTL = _find_prctl()


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies
    (``prctl(PR_SET_PDEATHSIG)``); False where that is not available."""
    if _PRCTL is None:
        return False
    return _PRCTL(PR_SET_PDEATHSIG, int(sig)) == 0


def _set_pdeathsig(sig: int) -> None:
    set_parent_death_signal(sig)


def die_with_parent() -> None:
    """In a child before ``exec`` (``preexec_fn``): receive SIGTERM when the parent dies
    (Linux), so that a killed launcher or monitor leaves nothing behind.  Elsewhere: nothing.
    Prefer :func:`tied_to_parent`, which also closes the race with a parent that dies
    before the child asks."""
    _set_pdeathsig(signal.SIGTERM)


def tied_to_parent(sig: int = signal.SIGTERM):
    """A ``preexec_fn`` that makes the child receive ``sig`` when this process dies (Linux
    ``PR_SET_PDEATHSIG``; nothing elsewhere).

    Called in the parent, it notes the parent's pid; in the child it asks for the signal,
    then exits at once if the parent is already gone (it died between ``fork`` and
    ``prctl``: the signal will never come).  Start children from the main thread: Linux
    sends the signal when the *thread* that forked the child ends.

    ``sig``: SIGTERM for a process that must close files on the way out (a stage closes
    its recording and says why), SIGKILL for one with nothing to save (the router, a check).
    """
    parent = os.getpid()

    def preexec() -> None:
        _set_pdeathsig(sig)
        if os.getppid() != parent:
            os._exit(1)

    return preexec


def start_child(cmd: list[str], log, env: dict, sig: int) -> subprocess.Popen:
    """Start ``cmd`` as a child the launcher supervises: its output to the open file ``log``, no
    standard input, ``sig`` when this process dies (:func:`tied_to_parent`), and a process
    group of its own, so that the terminal's Ctrl-C reaches the launcher alone, which stops
    the child in its own time."""
    return subprocess.Popen(
        cmd,
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        env=env,
        preexec_fn=tied_to_parent(sig),
        process_group=0,
    )


class SignalFlag:
    """SIGINT and SIGTERM noted by a handler that takes no lock.

    A Python signal handler runs in the main thread between two bytecodes, possibly in the
    middle of code holding a lock: a handler calling ``threading.Event.set()`` (which takes
    the Event's lock) deadlocks when the signal arrives while the main thread is inside
    ``Event.wait()`` holding it.  The handler here only stores the signal number (an
    attribute store: no lock, no logging); the main loop polls :attr:`received` or sleeps in
    :meth:`wait`, whose slices are short.

    Use as ``flag = SignalFlag().install()`` ... ``flag.restore()``; installing from a
    thread other than the main one does nothing (Python allows handlers there only).
    """

    def __init__(self, signals=(signal.SIGINT, signal.SIGTERM)):
        self.signals = tuple(signals)
        #: Number of the last signal received, or None.
        self.received: int | None = None
        self._previous: dict = {}

    def _handler(self, signum, frame) -> None:
        self.received = signum  # nothing else: see the class docstring

    def install(self) -> SignalFlag:
        if threading.current_thread() is threading.main_thread():
            for sig in self.signals:
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @property
    def name(self) -> str | None:
        """Name of the signal received (``"SIGTERM"``), or None."""
        return None if self.received is None else signal.Signals(self.received).name

    def __bool__(self) -> bool:
        return self.received is not None

    def wait(self, timeout: float, step: float = 0.1) -> bool:
        """Sleep until a signal came or ``timeout`` seconds passed; True when one came."""
        deadline = time.monotonic() + timeout
        while self.received is None:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            time.sleep(min(step, left))
        return True


def wait_port(port: int, timeout: float = 10.0, proc: subprocess.Popen | None = None, host: str = LOOPBACK) -> bool:
    """Wait until something accepts TCP connections on ``host:port``; False after ``timeout``
    seconds, or as soon as ``proc`` (the process expected to listen) has exited."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            return False
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return True
        time.sleep(0.1)
    return False


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """Terminate ``proc`` (a child we started), kill it if it does not exit in ``timeout`` s."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
