"""Child processes of the operations layer (router, stages, viewers): tie them to their
parent, wait until they listen, stop them."""

from __future__ import annotations

import ctypes
import signal
import socket
import subprocess
import time

from .session import LOOPBACK

#: ``prctl`` option that asks for a signal when the parent dies (Linux).
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """In a child before ``exec`` (``preexec_fn``): receive SIGTERM when the parent dies
    (Linux), so that a killed launcher or monitor leaves nothing behind.  Elsewhere: nothing."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    except (OSError, AttributeError):
        pass


def wait_port(port: int, timeout: float = 10.0, proc: subprocess.Popen | None = None,
              host: str = LOOPBACK) -> bool:
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
