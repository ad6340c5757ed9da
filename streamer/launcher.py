"""The launcher of ``ttl run``: starts the five stages as processes, supervises them, stops them.

Process model
-------------
* The launcher starts a Zenoh **router** process (``ttl router``, log in
  ``<recordings>/<run>/router.log``) listening on ``tls/127.0.0.1:<free port>`` (or
  ``--listen``), multicast scouting off, and talks to it as a client itself.
* Security (:mod:`streamer.security`): unless ``--insecure``, every session of the run uses
  mutual TLS with a certificate of the run's CA, taken from ``--credentials DIR`` or made on
  first use in ``<recordings>/<run>/credentials`` (keys mode 0600); the router enforces an
  access-control list (each stage publishes only its own topics, the launcher the
  commands).  Peers refused by the router and publications it dropped are read back from
  its log, reported and written to ``<recordings>/<run>/security.jsonl``.
* Each stage is a separate process, ``python -m stages.<name> --config
  <recordings>/<run>/<name>.config.json``, a Zenoh **client** of the router: every message
  goes through the router, and a stage whose link closed (a stall beyond
  :data:`streamer.session.BLOCK_WAIT_BEFORE_CLOSE`) reconnects and catches up from the
  publishers' caches.  (Peers would talk directly, but Zenoh does not re-establish a closed
  peer-to-peer link, and the router does not route between peers.)  Nothing listens on
  anything but 127.0.0.1 unless configured (``--listen``, ``--zenoh-config``).
* Stage logs go to ``<recordings>/<run>/<name>.log``, recordings to
  ``<recordings>/<run>/<name>.mcap`` (and ``monitor.rrd``).

Progress and completion
-----------------------
The pipeline stages publish cumulative progress on ``ttl/<run>/control/progress/<stage>``
(:mod:`streamer.progress`); the replayer's carries ``segments_total``.  The launcher keeps,
per stage, a :class:`streamer.progress.Progress`: the union of the indices handled over all
its processes (a restarted stage starts afresh), of the messages it believed (a stage may
not claim a segment its upstream has not handled, :data:`streamer.topology.UPSTREAM`).  It
republishes it on ``ttl/<run>/control/board/<stage>`` for the stages to follow, and shows
``done/total`` per stage, with liveliness (``ttl/<run>/alive/<stage>``).  When every stage
has handled every segment, the launcher sends ``ttl/<run>/control/stop``; the stages close
their recordings and exit 0, and so does ``ttl run``.

Supervision
-----------
A stage that exits before the stop is reported (exit status, last line of its log); with
``restart`` > 0 it is restarted (up to that many times per stage) and catches up from the
publishers' caches (the replayer stays within ``window`` segments of the slowest stage and
the caches hold ``cache`` > ``window`` + 1 segments); otherwise the run is stopped and
``ttl run`` exits 1.  ``external`` stages are expected but run elsewhere (``ttl stage``
on another host, or started later: late joiners catch up from the caches).

The Zenoh router is supervised too: when it dies, it is started again on the same endpoints
(up to ``restart`` times); the stages and the launcher, its clients, reconnect by themselves
and recover what was published meanwhile from the publishers' caches.

Journal and resuming
--------------------
The launcher appends what it does to ``<recordings>/<run>/launcher.jsonl`` (one JSON object
a line: ``start``, ``stage-died``, ``stage-restarted``, ``router-died``,
``router-restarted``, ``resume``, ``end``; ``ttl inspect`` lists them) and keeps the board
it believes in ``<recordings>/<run>/board.json``.  A launcher that died (SIGKILL: its stages
stop as orphaned, the router with it) is replaced by the same ``ttl run`` command with
``--resume``: it reads ``board.json``, takes every segment before the first one some stage
lacks (``m``) as handled by every stage, and starts the stages, which go on from there as
restarted stages do (the replayer from ``m - 1``, the fitter's window rebuilt from the
recordings); segments from ``m`` on are processed and published again, by every stage.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import queue
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh
from tqdm import tqdm

from ttlcore.effects import make_effects
from ttlcore.errors import TTLError

from . import security
from .keys import (
    ERRORS,
    board_key,
    check_name,
    control_key,
    errors_key,
    progress_key,
    progress_pattern,
    to_ranges,
    topic_pattern,
)
from .plan import RangeSet
from .processes import SignalFlag, stop_process, tied_to_parent
from .progress import REPLAY_WINDOW, Progress, key_stage, parse_progress
from .recorder import stage_record
from .session import (
    Bus,
    SessionSettings,
    declare_segment_publisher,
    declare_segment_subscriber,
    loopback_endpoint,
)
from .stage import LAUNCHER
from .topology import STAGE_PACKAGE, STAGES, UPSTREAM, stage_module

log = logging.getLogger(__name__)

#: Seconds a progress message claiming more than its upstream waits for the upstream's progress.
HOLD_PROGRESS = 30.0


class LaunchError(TTLError):
    """The run cannot start (message names the option, file or stage at fault)."""


@dataclass
class RunOptions:
    """What ``ttl run`` runs (command-line options, or a ``--config`` file with these keys).

    Attributes
    ----------
    run_id : str
    recordings : Path
    telemetry : list of str, optional
        Telemetry files (exclusive with ``simulate``).
    simulate : str, optional
        ``ttl simulate`` options.
    segment : str
        Segment length (``1h``, ``30min``, seconds).
    pace : float
        Multiple of real time (0: as fast as the consumers take the segments).
    window : int
        Segments the replayer may run ahead of the slowest stage.
    cache : int, optional
        Segments each stage keeps per output topic for late joiners (default window + 4).
    skip : tuple of str
        Stages not run at all.
    external : tuple of str
        Stages run elsewhere (expected, not started).
    restart : int
        Restarts allowed per stage.
    listen : tuple of str
        Router endpoints (default ``tcp/127.0.0.1:<free port>``).
    zenoh_config : Path, optional
        Zenoh configuration file of the router.
    credentials : Path, optional
        Credentials directory (default ``<recordings>/<run>/credentials``, made on first use).
    insecure : bool
        No TLS, no access control (plain TCP): any process reaching the router may publish.
    stage_options : dict
        Stage name -> stage options (``options`` of its StageConfig), and the fitter
        options ``fit_segment``, ``window_duration``, ``band``.
    timeout : float, optional
        Give up after this many seconds.
    resume : bool
        Go on with a run whose launcher died (``board.json`` of the run directory; module
        docstring, "Journal and resuming").
    """

    run_id: str
    recordings: Path = Path("recordings")
    telemetry: list | None = None
    simulate: str | None = None
    segment: str = "1h"
    pace: float = 0.0
    window: int = REPLAY_WINDOW
    cache: int | None = None
    skip: tuple = ()
    external: tuple = ()
    restart: int = 0
    listen: tuple = ()
    zenoh_config: Path | None = None
    credentials: Path | None = None
    insecure: bool = False
    stage_options: dict = field(default_factory=dict)
    timeout: float | None = None
    stop_timeout: float = 60.0
    resume: bool = False
    log_level: str = "INFO"
    quiet: bool = False
    python: str = sys.executable


def stage_module_exists(name: str) -> bool:
    """True when ``stages/<name>.py`` is installed (without importing it)."""
    spec = importlib.util.find_spec(STAGE_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return False
    return any(
        (Path(loc) / f"{name}.py").exists() or (Path(loc) / name / "__init__.py").exists()
        for loc in spec.submodule_search_locations
    )


@dataclass
class _Child:
    name: str
    config: Path
    log: Path
    proc: subprocess.Popen | None = None
    starts: int = 0
    exit_codes: list = field(default_factory=list)
    pids: set = field(default_factory=set)
    pids_order: list = field(default_factory=list)


class Launcher:
    """Runs one pipeline (see the module docstring); :meth:`run` returns the exit status."""

    def __init__(self, opts: RunOptions, out=None):
        self.opts = opts
        self.out = out or sys.stderr
        self.children: dict[str, _Child] = {}
        self.expected: list[str] = []
        self.alive: dict[str, bool] = {}
        self.progress: dict[str, Progress] = {}  # stage -> what the launcher believed of it
        self.errors: list[dict] = []
        self.events: queue.Queue = queue.Queue()
        self._t0 = time.monotonic()
        self._last_line = ""
        self._last_print = 0.0
        self._live: tqdm | None = None  # the status line, in place on a terminal
        self.endpoint = ""
        self.run_dir = Path(opts.recordings) / opts.run_id
        self.run_plan: dict | None = None
        self.refused_progress: list[dict] = []  # progress messages refused (forged or inconsistent)
        self._held: list[tuple[dict, float]] = []
        self._boards: dict = {}
        self.credentials: Path | None = None
        self.router: subprocess.Popen | None = None
        self.refused: list[dict] = []
        self._watcher: security.RefusalWatcher | None = None
        self.router_starts = 0
        self.resumed_from: int | None = None  # --resume: the first segment handled again

    # ------------------------------------------------------------------ output
    def say(self, text: str) -> None:
        msg = f"ttl run {self.opts.run_id}: {text}"
        if self._live is not None:  # above the status line, which stays at the bottom
            self._live.write(msg, file=self.out)
        else:
            print(msg, file=self.out, flush=True)

    # ------------------------------------------------------------------ validation
    def plan(self) -> None:
        o = self.opts
        try:
            check_name(o.run_id, "run id")
        except ValueError as exc:
            raise LaunchError(f"--run-id: {exc}") from None
        for what, names in (("--skip", o.skip), ("--external", o.external)):
            for n in names:
                if n not in STAGES:
                    raise LaunchError(f"{what}: unknown stage {n!r} (stages: {', '.join(STAGES)})")
        if "replayer" in o.skip:
            raise LaunchError("--skip: the replayer cannot be skipped (run it elsewhere with --external replayer)")
        if not o.telemetry and not o.simulate and "replayer" not in o.external:
            raise LaunchError('no telemetry source: give --telemetry FILE... or --simulate "<ttl simulate options>"')
        if o.telemetry and o.simulate:
            raise LaunchError("give either --telemetry or --simulate, not both")
        for f in o.telemetry or ():
            if not Path(f).is_file():
                raise LaunchError(f"--telemetry: {f}: no such file")
        secure = not o.insecure
        for e in o.listen:
            if secure and not str(e).startswith("tls/"):
                raise LaunchError(
                    f"--listen {e}: the run talks mutual TLS: write tls/{str(e).split('/', 1)[-1]} (or give --insecure)"
                )
        if o.insecure and o.credentials is not None:
            raise LaunchError("give either --credentials or --insecure, not both")
        if o.window < 1:
            raise LaunchError(f"--window: expected >= 1, got {o.window}")
        cache = self.cache
        if cache < o.window + 2:
            raise LaunchError(
                f"--cache: {cache} segments is too few for --window {o.window} "
                f"(a restarted stage needs at least window + 2 = {o.window + 2})"
            )
        skipped = set(o.skip)
        if "monitor" not in skipped and "monitor" not in o.external and not stage_module_exists("monitor"):
            self.say("the monitor stage (stages/monitor.py) is not installed: running without it")
            skipped.add("monitor")
        for name in STAGES:
            if name not in skipped and name not in o.external and not stage_module_exists(name):
                raise LaunchError(f"stage {name!r}: module stages.{name} not found")
        self.check_model()
        self.expected = [n for n in STAGES if n not in skipped]

    def check_model(self) -> None:
        """The fitter's model (``--effects``, ``--effect-module``) parsed here, before any
        work: a bad spec is refused in one line instead of a fitter that dies at start."""
        fitter = self.opts.stage_options.get("fitter") or {}
        effects = fitter.get("effects")
        if not effects:
            return
        specs = (
            [x.strip().replace(";", ",") for x in effects.split(",") if x.strip()]
            if isinstance(effects, str)
            else list(effects)
        )
        try:
            names = [e.name for e in make_effects(specs, tuple(fitter.get("effect_modules") or ()))]
        except TTLError as exc:
            raise LaunchError(f"--effects: {exc}") from None
        if "linear-ttl" not in names:
            raise LaunchError("--effects: the model must include linear-ttl")

    @property
    def cache(self) -> int:
        return self.opts.cache if self.opts.cache is not None else self.opts.window + 4

    def stage_options(self, name: str) -> dict:
        o = self.opts
        opts = dict(o.stage_options.get(name) or {})
        started = [n for n in self.expected if n not in o.external]
        if name == "replayer":
            # flow control on the stages started here that report progress, up to the first
            # external one: a stage downstream of an external stage cannot progress before that
            # one joins (it is followed once it reports progress)
            first_external = min((STAGES.index(n) for n in o.external), default=len(STAGES))
            opts.update(
                {
                    "telemetry": [str(Path(f).resolve()) for f in o.telemetry] if o.telemetry else None,
                    "simulate": o.simulate,
                    "segment": o.segment,
                    "pace": o.pace,
                    "window": o.window,
                    "wait_for": [n for n in started if n != "replayer"],
                    "pace_on": [n for n in started if n != "replayer" and STAGES.index(n) < first_external],
                }
            )
        return {k: v for k, v in opts.items() if v is not None}

    def stage_config(self, name: str) -> dict:
        cfg = {
            "run": self.opts.run_id,
            "stage": name,
            "zenoh": self.session_settings(name).to_dict(),
            "recordings": str(Path(self.opts.recordings).resolve()),
            "cache": self.cache,
            "options": self.stage_options(name),
            "plan": self.run_plan,
            "launcher_pid": os.getpid(),
            "progress_from": "launcher",
            # inputs recorded as headers only (a reference to the payload in the producer's
            # file): each payload is stored once per run
            "record_inputs": False,
        }
        return cfg

    def session_settings(self, identity: str) -> SessionSettings:
        """How ``identity`` (a stage, the launcher) connects to the run's router."""
        return SessionSettings(
            mode="client",
            connect=(self.endpoint,),
            credentials=self.credentials,
            identity=identity if self.credentials is not None else None,
        )

    # ------------------------------------------------------------------ journal, board, resume
    def journal(self, kind: str, message: str, **details) -> None:
        """Append a record to ``launcher.jsonl`` (module docstring; ``ttl inspect`` reads it)."""
        rec = {"time": time.time(), "launcher_pid": os.getpid(), "kind": kind, "message": message, **details}
        try:
            with open(self.run_dir / "launcher.jsonl", "a") as f:
                f.write(json.dumps(rec) + "\n")
        except OSError as exc:
            log.warning("cannot write %s: %s", self.run_dir / "launcher.jsonl", exc)

    def save_board(self) -> None:
        """Write the board (what the launcher believes of every stage) to ``board.json``,
        atomically: a launcher that dies leaves the last one whole."""
        path = self.run_dir / "board.json"
        tmp = path.with_name(".board.json.tmp")
        try:
            tmp.write_text(json.dumps({s: p.message(self.opts.run_id) for s, p in self.progress.items()}))
            os.replace(tmp, path)
        except OSError as exc:
            log.warning("cannot write %s: %s", path, exc)

    def load_board(self) -> None:
        """``--resume``: the progress of the earlier launcher (``board.json``), cut at the first
        segment some expected stage has not handled, so that every stage goes on from the
        same segment (the publishers' caches of the earlier processes are gone with them)."""
        path = self.run_dir / "board.json"
        try:
            board = json.loads(path.read_text())
        except FileNotFoundError:
            self.say(f"--resume: no {path}: the run starts from its first segment")
            board = {}
        except (OSError, ValueError) as exc:
            raise LaunchError(f"--resume: {path}: unreadable ({exc})") from None
        total = self.run_plan["segments_total"] if self.run_plan else None
        progress = {}
        for stage, msg in board.items():
            if stage in self.expected and isinstance(msg, dict):
                progress[stage] = Progress(stage)
                progress[stage].update(msg, total)

        def first_missing(stage: str) -> int:
            if stage not in progress or not total:
                return 0
            missing = progress[stage].handled.missing(0, total - 1)
            return missing[0][0] if missing else total

        def below(indices: RangeSet, first: int) -> RangeSet:
            out = RangeSet()
            for a, b in indices.ranges():
                if a < first:
                    out.add_range(a, min(b, first - 1))
            return out

        first = min(first_missing(s) for s in self.expected)
        self.resumed_from = first
        if first == 0:
            self.journal("resume", "resumed from segment 0 (nothing handled by every stage)", first=0)
            return
        for stage, p in progress.items():
            self.progress[stage] = Progress(
                stage,
                below(p.done, first),
                below(p.failed, first),
                total,
                below(p.gaps, first),
                extra={n: below(v, first) for n, v in p.extra.items()},
            )
        self.say(f"--resume: segments 0..{first - 1} handled by every stage (board.json); going on from {first}")
        self.journal(
            "resume", f"resumed: segments 0..{first - 1} handled by every stage; going on from {first}", first=first
        )

    # ------------------------------------------------------------------ router and credentials
    def make_credentials(self, listen) -> None:
        """The run's credentials (``--credentials`` or made in the run directory), unless insecure."""
        o = self.opts
        if o.insecure:
            self.say("--insecure: no TLS, no access control; any process reaching the router may publish")
            return
        hosts = [security.endpoint_host(e) for e in listen]
        hosts = [h for h in hosts if h and h not in security.LOCAL_HOSTS and h not in ("0.0.0.0", "[::]", "::")]
        directory = Path(o.credentials) if o.credentials is not None else self.run_dir / "credentials"
        fresh = not (directory / "ca.pem").exists()
        try:
            self.credentials = security.ensure_credentials(directory, hosts=hosts).resolve()
            for role in ("router", "launcher", *self.expected):
                security.Identity(self.credentials, role).check()
        except security.CredentialsError as exc:
            raise LaunchError(f"--credentials: {exc}") from None
        if fresh:
            self.say(f"credentials made in {directory} (CA and one certificate per stage)")

    def start_router(self, listen) -> None:
        """Start ``ttl router`` (log ``router.log``) and wait until it listens."""
        o = self.opts
        path = self.run_dir / "router.log"
        cmd = [o.python, "-c", "import sys; from streamer.cli import main; sys.exit(main())", "router"]
        for e in listen:
            cmd += ["--listen", e]
        if o.zenoh_config is not None:
            cmd += ["--zenoh-config", str(o.zenoh_config)]
        cmd += ["--credentials", str(self.credentials)] if self.credentials is not None else ["--insecure"]
        env = dict(os.environ, PYTHONUNBUFFERED="1", NO_COLOR="1")
        env.pop("RUST_LOG", None)
        with open(path, "ab") as logf:
            start = logf.tell()
            self.router = subprocess.Popen(
                cmd,
                stdout=logf,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                preexec_fn=tied_to_parent(signal.SIGKILL),
            )
        self.router_starts += 1
        self._watcher = security.RefusalWatcher(path, offset=start)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            text = path.read_text(errors="replace")[start:]
            if "ttl router: zenoh router" in text:
                return
            if self.router.poll() is not None:
                lines = [ln for ln in text.splitlines() if ln.strip()]
                raise LaunchError(
                    f"cannot open the Zenoh router on {', '.join(listen)}: "
                    f"{lines[-1] if lines else f'exit status {self.router.returncode}'}"
                )
            time.sleep(0.05)
        raise LaunchError(f"the Zenoh router did not start within 60 s (log {path})")

    def restart_router(self) -> str | None:
        """The router died: start it again on the same endpoints (up to ``restart`` times);
        returns a reason to abort, or None.  Its clients reconnect by themselves."""
        code = self.router.returncode
        how = (
            f"killed by {signal.Signals(-code).name}"
            if code < 0 and -code in signal.Signals._value2member_map_
            else f"exit status {code}"
        )
        self.say(f"the Zenoh router died ({how}; log {self.run_dir / 'router.log'})")
        self.journal(
            "router-died",
            f"the Zenoh router (pid {self.router.pid}) died ({how})",
            stage="router",
            pid=self.router.pid,
            how=how,
        )
        self.watch_refusals()  # what the old router logged, before the new watcher starts
        if self.router_starts > self.opts.restart:
            return f"the Zenoh router died ({how}; log {self.run_dir / 'router.log'})"
        self.say(f"restarting the Zenoh router ({self.router_starts}/{self.opts.restart})")
        for attempt in range(5):  # the port of the killed router may take a moment to be free
            try:
                self.start_router(self.listen)
                break
            except LaunchError as exc:
                if attempt == 4:
                    return f"the Zenoh router could not be restarted: {exc}"
                time.sleep(1.0)
        self.journal(
            "router-restarted",
            f"the Zenoh router restarted (pid {self.router.pid})",
            stage="router",
            pid=self.router.pid,
            start=self.router_starts,
        )
        return None

    def stop_router(self) -> None:
        if self.router is None:
            return
        stop_process(self.router, 15.0)
        self.router = None

    def watch_refusals(self) -> None:
        """Report peers and publications the router refused (from its log)."""
        if self._watcher is None:
            return
        for r in self._watcher.poll():
            self.refused.append(r)
            if r["kind"] == "forbidden":
                self.say(f"refused: {r['subject']} may not {r['action']} on {r['key']}")
            else:
                self.say(f"refused a connection: {r['message']}")

    def check_replayer(self) -> None:
        """Validate the source options in a child (``stages.replayer --check``)."""
        if "replayer" in self.opts.external:
            return
        # in a scratch directory: nothing is written into the run's directory before the check passes
        with tempfile.TemporaryDirectory(prefix="ttl-check-") as scratch:
            path = Path(scratch) / "replayer.config.json"
            plan_path = Path(scratch) / "plan.json"
            path.write_text(json.dumps(self.stage_config("replayer"), indent=2))
            res = subprocess.run(
                [
                    self.opts.python,
                    "-m",
                    stage_module("replayer"),
                    "--config",
                    str(path),
                    "--check",
                    "--plan-out",
                    str(plan_path),
                    "--log-level",
                    "WARNING",
                ],
                capture_output=True,
                text=True,
                timeout=300,
                # nothing to save: killed with a killed or terminated launcher
                preexec_fn=tied_to_parent(signal.SIGKILL),
            )
            if res.returncode != 0:
                lines = [ln for ln in (res.stderr or res.stdout).strip().splitlines() if ln.strip()]
                msg = lines[-1] if lines else f"exit status {res.returncode}"
                raise LaunchError(msg.replace("ttl stage replayer: error: ", ""))
            self.run_plan = json.loads(plan_path.read_text())
        self.say(f"replay: {res.stdout.strip()}")

    # ------------------------------------------------------------------ bus callbacks
    def _on_progress(self, sample) -> None:
        msg = parse_progress(sample.payload)
        if msg is None:
            return
        stage = key_stage(str(sample.key_expr))
        if msg["stage"] != stage:  # the key is what the access-control list vouches for
            self.events.put(
                (
                    "error",
                    {
                        "stage": stage,
                        "kind": "forged-progress",
                        "key": str(sample.key_expr),
                        "message": f"progress of {msg['stage']!r} published as {stage!r}",
                    },
                )
            )
            return
        self.events.put(("progress", msg))

    def _on_alive(self, stage: str, alive: bool) -> None:
        self.events.put(("alive", stage, alive))

    def _on_error(self, sample) -> None:
        try:
            self.events.put(("error", json.loads(sample.payload.to_bytes())))
        except (ValueError, RecursionError):  # RecursionError: nested too deep for the parser
            self.events.put(("error", {"message": "unreadable error message", "key": str(sample.key_expr)}))

    def _drain_events(self) -> bool:
        changed = False
        while True:
            try:
                ev = self.events.get_nowait()
            except queue.Empty:
                return changed
            changed = True
            if ev[0] == "progress":
                msg, since = ev[1], (ev[2] if len(ev) > 2 else time.monotonic())
                why = self.progress_refused(msg)
                if why and "has not handled" in why and time.monotonic() - since < HOLD_PROGRESS:
                    self._held.append((msg, since))
                    continue
                if why:
                    self.refuse_progress(msg, why)
                    continue
                self.progress.setdefault(msg["stage"], Progress(msg["stage"])).update(
                    msg, self.run_plan["segments_total"] if self.run_plan else None
                )
                self.publish_board(msg["stage"])
            elif ev[0] == "alive":
                _, stage, alive = ev
                if stage in self.expected and self.alive.get(stage) != alive:
                    log.info("%s %s", stage, "alive" if alive else "gone")
                self.alive[stage] = alive
            elif ev[0] == "error":
                err = ev[1]
                self.errors.append(err)
                where = f" segment {err.get('index')}" if err.get("index") is not None else ""
                self.say(f"error from {err.get('stage', '?')}{where}: {err.get('kind', '')}: {err.get('message', '')}")

    def progress_refused(self, msg: dict) -> str | None:
        """Why a progress message is not believed, or None.  A stage started here must report
        with its own process id; ``segments_total`` must be the plan's; a stage may not claim
        a segment its upstream has not handled (progress of a stage started here is checked
        against the one before it in the pipeline)."""
        stage = msg["stage"]
        if stage not in self.expected:
            return f"progress of unknown stage {stage!r}"
        child = self.children.get(stage)
        if child is not None and child.proc is not None and msg.get("pid") not in child.pids:
            return f"pid {msg.get('pid')!r} is not the {stage} process started by this launcher"
        if self.run_plan and msg.get("segments_total") not in (None, self.run_plan["segments_total"]):
            return f"segments_total {msg.get('segments_total')!r} differs from the plan's {self.run_plan['segments_total']}"
        upstream = UPSTREAM.get(stage)
        if upstream in self.expected:
            claims = Progress(stage)
            claims.update(msg, self.run_plan["segments_total"] if self.run_plan else None)
            beyond = claims.handled - self.handled(upstream)
            if beyond:
                return f"claims segment(s) {to_ranges(beyond)[:5]} that {upstream} has not handled"
        return None

    def _recheck_held(self) -> None:
        """Progress held back for claiming more than its upstream: believed once the upstream's
        progress catches up (messages of different keys may arrive out of order), refused after
        ``HOLD_PROGRESS`` seconds."""
        held, self._held = self._held, []
        for msg, since in held:
            self.events.put(("progress", msg, since))

    def publish_board(self, stage: str) -> None:
        """Publish what the launcher believes of ``stage``'s progress (the union over its
        processes of the messages it accepted) on ``ttl/<run>/control/board/<stage>``: the
        pipeline stages of a launched run follow these, not the stages' own messages."""
        pub = self._boards.get(stage)
        if pub is None:
            pub = self._boards[stage] = self.bus.track(
                declare_segment_publisher(self.bus.session, board_key(self.opts.run_id, stage), cache=1)
            )
        pub.put(json.dumps(self.progress[stage].message(self.opts.run_id)).encode())
        self.save_board()

    def refuse_progress(self, msg: dict, why: str) -> None:
        """Record a refused progress message (shown, kept for the report, put on errors)."""
        err = stage_record(
            self.opts.run_id,
            LAUNCHER,
            "forged",
            f"progress message refused: {why}",
            details={"pid": msg.get("pid")},
            key=progress_key(self.opts.run_id, msg["stage"]),
            field="progress",
        )
        self.refused_progress.append(err)
        if len(self.refused_progress) <= 20:
            self.say(err["message"])
        try:
            self.bus.put_json(errors_key(self.opts.run_id, None), err)
        except Exception:  # noqa: BLE001 - the session may be closing
            pass

    # ------------------------------------------------------------------ state
    @property
    def total(self) -> int | None:
        if self.run_plan:
            return self.run_plan["segments_total"]
        totals = [p.segments_total for p in self.progress.values() if p.segments_total]
        return max(totals) if totals else None

    def handled(self, stage: str) -> set:
        p = self.progress.get(stage)
        return p.handled if p is not None else set()

    def stage_done(self, stage: str) -> bool:
        """``stage`` has handled every segment of the run."""
        p = self.progress.get(stage)
        return p is not None and p.covers(self.total)

    def status_line(self) -> str:
        total = self.total
        parts = []
        for s in self.expected:
            n = len(self.handled(s))
            mark = "" if self.alive.get(s) else " (down)" if s in self.alive else " (not up)"
            parts.append(f"{s} {n}/{total if total is not None else '?'}{mark}")
        return " | ".join(parts) + f"  [{time.monotonic() - self._t0:.1f} s]"

    def show(self, force: bool = False) -> None:
        """The stages' progress: one line updated in place on a terminal, a new line at most
        every second when it changed in a log (``force``: the final state, printed to stay)."""
        if self.opts.quiet:
            return
        line = self.status_line()
        if self._live is not None or (hasattr(self.out, "isatty") and self.out.isatty()):
            if self._live is None:
                self._live = tqdm(total=None, file=self.out, bar_format="{desc}", leave=True, dynamic_ncols=True)
            self._live.set_description_str(f"ttl run {self.opts.run_id}: {line}")
            if force:
                self.end_status_line()
            return
        now = time.monotonic()
        core = line.rsplit("  [", 1)[0]
        if force or (core != self._last_line and now - self._last_print >= 1.0):
            self._last_line, self._last_print = core, now
            self.say(line)

    def end_status_line(self) -> None:
        """Leave the in-place status line as it is and go on below it."""
        if self._live is not None:
            self._live.close()
            self._live = None

    # ------------------------------------------------------------------ children
    def start(self, name: str) -> None:
        child = self.children[name]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if name == "monitor":  # small linear algebra: threaded BLAS only fights the other stages for the cores
            env.setdefault("OPENBLAS_NUM_THREADS", "1")
        with open(child.log, "ab") as logf:
            logf.write(f"--- start {child.starts + 1} of {name} at {time.ctime()} ---\n".encode())
            logf.flush()
            child.proc = subprocess.Popen(
                [
                    self.opts.python,
                    "-m",
                    stage_module(name),
                    "--config",
                    str(child.config),
                    "--log-level",
                    self.opts.log_level,
                ],
                stdout=logf,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                # SIGTERM when the launcher dies, even while importing or opening its session
                # (the stage then closes its recording, saying it was orphaned)
                preexec_fn=tied_to_parent(signal.SIGTERM),
            )
        child.starts += 1
        child.pids.add(child.proc.pid)
        child.pids_order.append(child.proc.pid)
        log.info("started %s (pid %d)", name, child.proc.pid)

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
            how = (
                f"killed by {signal.Signals(-code).name}"
                if code < 0 and -code in signal.Signals._value2member_map_
                else f"exit status {code}" + {3: ": orphaned", 4: ": disk full"}.get(code, "")
            )
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
                self.start(name)
                self.journal(
                    "stage-restarted",
                    f"stage {name} restarted (pid {child.proc.pid})",
                    stage=name,
                    pid=child.proc.pid,
                    start=child.starts,
                )
            else:
                return f"stage {name} died ({how})"
        return None

    def stop_all(self) -> None:
        """Ask every stage to stop, wait, then terminate and kill what is left."""
        try:
            self.bus.session.put(
                control_key(self.opts.run_id, "stop"), b"{}", congestion_control=zenoh.CongestionControl.BLOCK
            )
        except Exception as exc:  # session closed
            log.warning("could not send stop: %s", exc)
        deadline = time.monotonic() + self.opts.stop_timeout
        for sig, wait in ((None, None), (signal.SIGTERM, 15.0), (signal.SIGKILL, 10.0)):
            running = [c for c in self.children.values() if c.proc is not None and c.proc.poll() is None]
            if not running:
                break
            if sig is not None:
                for c in running:
                    self.say(f"stage {c.name} did not stop: sending {sig.name}")
                    c.proc.send_signal(sig)
                deadline = time.monotonic() + wait
            for c in running:
                try:
                    c.proc.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for c in self.children.values():
            if c.proc is not None:
                c.exit_codes.append(c.proc.returncode)
                c.proc = None

    # ------------------------------------------------------------------ the run
    def run(self) -> int:
        o = self.opts
        self.plan()
        listen = tuple(o.listen) or (loopback_endpoint(protocol="tcp" if o.insecure else "tls"),)
        self.endpoint = next((e for e in listen if "127.0.0.1" in e or "localhost" in e), listen[0])
        self.listen = listen
        # the source (--simulate, --telemetry) is checked before the run directory, its
        # credentials or configs are made: a refused run leaves nothing behind
        self.check_replayer()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if self.run_plan is not None:
            (self.run_dir / "plan.json").write_text(json.dumps(self.run_plan, indent=2))
        self.make_credentials(listen)
        self.journal(
            "start",
            f"ttl run started (pid {os.getpid()})" + (" with --resume" if o.resume else ""),
            resume=bool(o.resume),
        )
        if o.resume:
            self.load_board()
        self.start_router(listen)
        try:
            try:
                bus = Bus.open(self.session_settings("launcher"))
            except Exception as exc:
                raise LaunchError(f"cannot reach the run's router at {self.endpoint}: {exc}") from None
            with bus:
                status = self._run_on(bus)
                self.journal("end", f"ttl run ended (exit status {status})", status=status)
                return status
        finally:
            self.stop_router()
            self.watch_refusals()
            if self._watcher is not None and self.credentials is not None:
                security.dump(self.refused, self.run_dir / "security.jsonl")

    def _run_on(self, bus: Bus) -> int:
        o = self.opts
        self.bus = bus
        bus.track(declare_segment_subscriber(bus.session, progress_pattern(o.run_id), self._on_progress, history=1))
        bus.watch_alive(o.run_id, self._on_alive)
        # the stages stop when this token goes (streamer.stage.Stage.orphaned)
        bus.declare_alive(o.run_id, LAUNCHER)
        bus.subscriber(topic_pattern(o.run_id, ERRORS), self._on_error)
        for stage in list(self.progress):  # --resume: the board of the earlier launcher, cut
            self.publish_board(stage)
        security_note = "" if self.credentials is None else f" (mutual TLS, credentials {self.credentials})"
        self.say(
            f"router on {', '.join(self.listen)}{security_note}; stages: {', '.join(self.expected)}"
            + (f" (external: {', '.join(o.external)})" if o.external else "")
            + f"; recordings in {self.run_dir}"
        )
        for name in reversed(self.expected):  # consumers first, the replayer last
            if name in o.external:
                continue
            cfg = self.run_dir / f"{name}.config.json"
            cfg.write_text(json.dumps(self.stage_config(name), indent=2))
            self.children[name] = _Child(name, cfg, self.run_dir / f"{name}.log")
            self.start(name)
        return self._supervise_loop()

    def _supervise_loop(self) -> int:
        o = self.opts
        deadline = time.monotonic() + o.timeout if o.timeout else None
        abort = None
        # SIGTERM: stop the stages first (a flag: no lock taken in the handler)
        terminated = SignalFlag((signal.SIGTERM,)).install()
        try:
            while True:
                if terminated:
                    abort = "terminated"
                    break
                self._drain_events()
                self._recheck_held()
                self.watch_refusals()
                abort = self.supervise()
                if not abort and self.router is not None and self.router.poll() is not None:
                    abort = self.restart_router()
                if abort:
                    break
                self.show()
                if self.total is not None and all(self.stage_done(s) for s in self.expected):
                    self.show(force=True)
                    self.say("every stage has handled every segment: stopping")
                    break
                if deadline is not None and time.monotonic() > deadline:
                    abort = f"timed out after {o.timeout:g} s"
                    break
                time.sleep(0.1)
        except KeyboardInterrupt:
            abort = "interrupted"
        finally:
            terminated.restore()
        self.stop_all()
        self._drain_events()
        return self.report(abort)

    def conflicts(self) -> list[str]:
        """The segments (``topic/index``, by first report) of which a stage reported
        conflicting copies (error ``kind: conflict`` on the errors topic)."""
        seen: dict[str, None] = {}
        for err in self.errors:
            if isinstance(err, dict) and err.get("kind") == "conflict":
                key = str(err.get("key") or "")
                seen.setdefault("/".join(key.split("/")[2:]) or f"segment {err.get('index')}", None)
        return list(seen)

    def report(self, abort: str | None) -> int:
        self.end_status_line()
        total = self.total
        status = 0
        for name, child in self.children.items():
            bad = [c for c in child.exit_codes[-1:] if c != 0]
            if bad:
                self.say(f"stage {name} exited with status {bad[0]} (log {child.log})")
                status = 1
        for s in self.expected:
            p = self.progress.get(s) or Progress(s)
            gaps = sorted(p.gaps)
            failed = sorted(p.failed - p.gaps)
            if gaps:
                self.say(f"stage {s}: gap(s) in the data at segment(s) {to_ranges(gaps)} (no data; reported)")
            if failed:
                self.say(f"stage {s} gave up segment(s) {failed}")
                status = 1
            if total is not None and s in self.progress and not self.handled(s).issuperset(range(total)):
                missing = sorted(set(range(total)) - self.handled(s))
                self.say(f"stage {s} did not handle segment(s) {missing[:20]}{' ...' if len(missing) > 20 else ''}")
                status = 1
        conflicts = self.conflicts()
        if conflicts:
            # two different copies of a segment were published: one of them was not the
            # producer's (docs/operations.md, "Conflicting copies"), whatever was used
            self.say(
                f"conflicting copies of {len(conflicts)} segment(s) received: "
                + ", ".join(conflicts[:10])
                + (" ..." if len(conflicts) > 10 else "")
            )
            status = 1
        if abort:
            self.say(f"run stopped: {abort}")
            return {"interrupted": 130, "terminated": 143}.get(abort, 1)
        files = sorted(p.name for p in self.run_dir.glob("*.mcap")) + sorted(p.name for p in self.run_dir.glob("*.rrd"))
        refused = f", {len(self.refused)} refusal(s) by the router (security.jsonl)" if self.refused else ""
        # the counts also when the run failed (exit 1): what went wrong is above, how much here
        self.say(
            f"{'done' if status == 0 else 'ended (exit status 1)'}: {total} segments, "
            f"{len(self.errors)} error report(s){refused}, {len(self.refused_progress)} progress message(s) "
            f"refused; files in {self.run_dir}: {', '.join(files)}"
        )
        return status


def run(opts: RunOptions, out=None) -> int:
    """Run a pipeline (``ttl run``); returns the exit status."""
    return Launcher(opts, out).run()
