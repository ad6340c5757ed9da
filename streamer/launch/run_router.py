"""The Zenoh router of a ``ttl run`` and the run's credentials.

The router is a child process (``ttl router``, log ``<run>/router.log``) that dies with the
launcher (SIGKILL: nothing to save), in a process group of its own (a Ctrl-C in the terminal
does not reach it: the launcher stops it last); when it dies during the run it is started
again on the same endpoints (:meth:`Router.restart`).  Peers and publications it refused are read back
from its log (:class:`streamer.bus.security.RefusalWatcher`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ..bus import security
from ..runtime.processes import start_child, stop_process
from .launch_plan import LaunchError, RunOptions


def exit_description(code: int) -> str:
    """``killed by SIGKILL`` or ``exit status <code>`` for a child's return code."""
    if code < 0 and -code in signal.Signals._value2member_map_:
        return f"killed by {signal.Signals(-code).name}"
    return f"exit status {code}"


def make_credentials(
    o: RunOptions, run_dir: Path, roles: Sequence[str], listen, say: Callable[[str], None], warn: Callable[[str], None]
) -> Path | None:
    """The run's credentials (``--credentials`` or made in ``<run_dir>/credentials``, with a
    certificate for every role), unless insecure (None): ``say`` tells of credentials made,
    ``warn`` that there are none (a warning, printed under ``--quiet`` too)."""
    if o.insecure:
        warn("--insecure: no TLS, no access control; any process reaching the router may publish")
        return None
    hosts = [security.endpoint_host(e) for e in listen]
    hosts = [h for h in hosts if h and h not in security.LOCAL_HOSTS and h not in ("0.0.0.0", "[::]", "::")]
    directory = Path(o.credentials) if o.credentials is not None else run_dir / "credentials"
    fresh = not (directory / "ca.pem").exists()
    try:
        credentials = security.ensure_credentials(directory, hosts=hosts).resolve()
        for role in ("router", "launcher", *roles):
            security.Identity(credentials, role).check()
    except security.CredentialsError as exc:
        raise LaunchError(f"--credentials: {exc}") from None
    if fresh:
        say(f"credentials made in {directory} (CA and one certificate per stage)")
    return credentials


class Router:
    """The run's router process.

    Parameters
    ----------
    opts : RunOptions
        ``python``, ``zenoh_config`` and ``restart`` (restarts allowed).
    run_dir : Path
        The run directory (``router.log``).
    credentials : Path or None
        The run's credentials (None: ``--insecure``).
    say, journal : callable
        The launcher's console line and journal record.
    """

    def __init__(self, opts: RunOptions, run_dir: Path, credentials: Path | None, say, journal):
        self.opts = opts
        self.run_dir = run_dir
        self.credentials = credentials
        self.say = say
        self.journal = journal
        self.proc: subprocess.Popen | None = None
        self.listen: tuple = ()
        self.starts = 0
        #: Peers and publications refused, from the router's log.
        self.refused: list[dict] = []
        self.watcher: security.RefusalWatcher | None = None

    def start(self, listen) -> None:
        """Start ``ttl router`` (log ``router.log``) and wait until it listens."""
        o = self.opts
        self.listen = tuple(listen)
        path = self.run_dir / "router.log"
        cmd = [o.python, "-c", "import sys; from streamer.tools.cli import main; sys.exit(main())", "router"]
        for e in listen:
            cmd += ["--listen", e]
        if o.zenoh_config is not None:
            cmd += ["--zenoh-config", str(o.zenoh_config)]
        cmd += ["--credentials", str(self.credentials)] if self.credentials is not None else ["--insecure"]
        env = dict(os.environ, PYTHONUNBUFFERED="1", NO_COLOR="1")
        env.pop("RUST_LOG", None)
        with open(path, "ab") as logf:
            start = logf.tell()
            # SIGKILL: nothing to save; the launcher stops it after the stages
            proc = self.proc = start_child(cmd, logf, env, signal.SIGKILL)
        self.starts += 1
        self.watcher = security.RefusalWatcher(path, offset=start)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            text = path.read_text(errors="replace")[start:]
            if "ttl router: zenoh router" in text:
                return
            if proc.poll() is not None:
                lines = [ln for ln in text.splitlines() if ln.strip()]
                raise LaunchError(
                    f"cannot open the Zenoh router on {', '.join(listen)}: "
                    f"{lines[-1] if lines else f'exit status {proc.returncode}'}"
                )
            time.sleep(0.05)
        raise LaunchError(f"the Zenoh router did not start within 60 s (log {path})")

    @property
    def process(self) -> subprocess.Popen:
        """The router's process (a RuntimeError before :meth:`start`)."""
        if self.proc is None:
            raise RuntimeError("the Zenoh router is used before it was started")
        return self.proc

    def died(self) -> bool:
        """The router was started and has exited."""
        return self.proc is not None and self.proc.poll() is not None

    def restart(self) -> str | None:
        """The router died: start it again on the same endpoints (up to ``restart`` times);
        returns a reason to abort, or None.  Its clients reconnect by themselves."""
        how = exit_description(self.process.returncode)
        self.say(f"the Zenoh router died ({how}; log {self.run_dir / 'router.log'})")
        self.journal(
            "router-died",
            f"the Zenoh router (pid {self.process.pid}) died ({how})",
            stage="router",
            pid=self.process.pid,
            how=how,
        )
        self.watch_refusals()  # what the old router logged, before the new watcher starts
        if self.starts > self.opts.restart:
            return f"the Zenoh router died ({how}; log {self.run_dir / 'router.log'})"
        self.say(f"restarting the Zenoh router ({self.starts}/{self.opts.restart})")
        for attempt in range(5):  # the port of the killed router may take a moment to be free
            try:
                self.start(self.listen)
                break
            except LaunchError as exc:
                if attempt == 4:
                    return f"the Zenoh router could not be restarted: {exc}"
                time.sleep(1.0)
        self.journal(
            "router-restarted",
            f"the Zenoh router restarted (pid {self.process.pid})",
            stage="router",
            pid=self.process.pid,
            start=self.starts,
        )
        return None

    def stop(self) -> None:
        if self.proc is None:
            return
        stop_process(self.proc, 15.0)
        self.proc = None

    def watch_refusals(self) -> None:
        """Report peers and publications the router refused (from its log)."""
        if self.watcher is None:
            return
        for r in self.watcher.poll():
            self.refused.append(r)
            if r["kind"] == "forbidden":
                self.say(f"refused: {r['subject']} may not {r['action']} on {r['key']}")
            else:
                self.say(f"refused a connection: {r['message']}")
