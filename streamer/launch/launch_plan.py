"""Planning a run of ``ttl run``: its options (:class:`RunOptions`), their checks, and the
configuration each stage process is started with.

Nothing here starts a process but :func:`check_replayer` (the replayer's ``--check``, in a
scratch directory): a run refused here leaves nothing behind.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ttlcore.effects import make_effects
from ttlcore.errors import TTLError

from ..bus.keys import check_name
from ..bus.topology import STAGE_PACKAGE, STAGES, stage_module
from ..runtime.processes import tied_to_parent
from ..runtime.progress import REPLAY_WINDOW
from ..runtime.settings import above, at_least, check_fields, from_dict, to_dict


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
    telemetry: list[str | Path] | None = None
    simulate: str | None = None
    segment: str | float = "1h"
    pace: float = field(default=0.0, metadata={"check": at_least(0)})
    window: int = REPLAY_WINDOW
    cache: int | None = None
    skip: tuple[str, ...] = ()
    external: tuple[str, ...] = ()
    restart: int = field(default=0, metadata={"check": at_least(0)})
    listen: tuple[str, ...] = ()
    zenoh_config: Path | None = None
    credentials: Path | None = None
    insecure: bool = False
    stage_options: dict[str, Any] = field(default_factory=dict)
    timeout: float | None = field(default=None, metadata={"check": above(0)})
    stop_timeout: float = field(default=60.0, metadata={"check": at_least(0)})
    resume: bool = False
    log_level: str = "INFO"
    quiet: bool = False
    python: str = sys.executable

    def __post_init__(self) -> None:
        check_fields(self, "run options")

    def to_dict(self) -> dict:
        """The JSON form (the keys of a ``ttl run --config`` file)."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunOptions:
        """Inverse of :meth:`to_dict`; a field that is unknown, missing or does not fit
        raises :class:`streamer.runtime.settings.SettingsError` naming it."""
        return from_dict(cls, d, "run options")


def stage_module_exists(name: str) -> bool:
    """True when ``stages/<name>.py`` is installed (without importing it)."""
    spec = importlib.util.find_spec(STAGE_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return False
    return any(
        (Path(loc) / f"{name}.py").exists() or (Path(loc) / name / "__init__.py").exists()
        for loc in spec.submodule_search_locations
    )


def cache_size(o: RunOptions) -> int:
    """Segments each stage keeps per output topic (``--cache``, default window + 4)."""
    return o.cache if o.cache is not None else o.window + 4


def expected_stages(o: RunOptions, say: Callable[[str], None]) -> list[str]:
    """Check the options; returns the stages of the run (run here or ``external``).

    Raises
    ------
    LaunchError
        Naming the option at fault.
    """
    try:
        check_name(o.run_id, "run id")
    except ValueError as exc:
        raise LaunchError(f"--run-id: {exc}") from None
    _check_stage_names(o)
    _check_source(o)
    _check_transport(o)
    skipped = set(o.skip)
    if "monitor" not in skipped and "monitor" not in o.external and not stage_module_exists("monitor"):
        say("the monitor stage (stages/monitor/monitor.py) is not installed: running without it")
        skipped.add("monitor")
    for name in STAGES:
        if name not in skipped and name not in o.external and not stage_module_exists(name):
            raise LaunchError(f"stage {name!r}: module stages.{name} not found")
    check_model(o)
    return [n for n in STAGES if n not in skipped]


def _check_stage_names(o: RunOptions) -> None:
    """``--skip`` and ``--external`` name stages, and the replayer is not skipped."""
    for what, names in (("--skip", o.skip), ("--external", o.external)):
        for n in names:
            if n not in STAGES:
                raise LaunchError(f"{what}: unknown stage {n!r} (stages: {', '.join(STAGES)})")
    if "replayer" in o.skip:
        raise LaunchError("--skip: the replayer cannot be skipped (run it elsewhere with --external replayer)")


def _check_source(o: RunOptions) -> None:
    """One telemetry source: files that exist, or a simulation (or an external replayer)."""
    if not o.telemetry and not o.simulate and "replayer" not in o.external:
        raise LaunchError('no telemetry source: give --telemetry FILE... or --simulate "<ttl simulate options>"')
    if o.telemetry and o.simulate:
        raise LaunchError("give either --telemetry or --simulate, not both")
    for f in o.telemetry or ():
        if not Path(f).is_file():
            raise LaunchError(f"--telemetry: {f}: no such file")


def _check_transport(o: RunOptions) -> None:
    """TLS endpoints unless ``--insecure`` (not with credentials), and a window and cache
    that let a restarted stage catch up."""
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
    cache = cache_size(o)
    if cache < o.window + 2:
        raise LaunchError(
            f"--cache: {cache} segments is too few for --window {o.window} "
            f"(a restarted stage needs at least window + 2 = {o.window + 2})"
        )


def check_model(o: RunOptions) -> None:
    """The fitter's model (``--effects``, ``--effect-module``) parsed here, before any
    work: a bad spec is refused in one line instead of a fitter that dies at start."""
    fitter = o.stage_options.get("fitter") or {}
    effects = fitter.get("effects")
    if not effects:
        return
    modules = tuple(fitter.get("effect_modules") or ())
    try:  # one string in the grammar of --effects, or a list of specs (docs/cli.md, "Effect specs")
        names = [e.name for e in make_effects(effects if isinstance(effects, str) else list(effects), modules)]
    except TTLError as exc:
        raise LaunchError(f"--effects: {exc}") from None
    if "linear-ttl" not in names:
        raise LaunchError("--effects: the model must include linear-ttl")


def stage_options(o: RunOptions, expected: list[str], name: str) -> dict:
    """The ``options`` of stage ``name``'s configuration (the replayer's flow control included)."""
    opts = dict(o.stage_options.get(name) or {})
    started = [n for n in expected if n not in o.external]
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


def stage_config(o: RunOptions, expected: list[str], name: str, zenoh: dict, plan: dict | None) -> dict:
    """The configuration file of stage ``name`` (:class:`streamer.runtime.stage_config.StageConfig` fields)."""
    return {
        "run": o.run_id,
        "stage": name,
        "zenoh": zenoh,
        "recordings": str(Path(o.recordings).resolve()),
        "cache": cache_size(o),
        "options": stage_options(o, expected, name),
        "plan": plan,
        "launcher_pid": os.getpid(),
        "progress_from": "launcher",
        # inputs recorded as headers only (a reference to the payload in the producer's
        # file): each payload is stored once per run
        "record_inputs": False,
    }


def check_replayer(o: RunOptions, config: dict) -> tuple[dict, str]:
    """Validate the source options in a child (``stages.replayer --check`` with the
    replayer's ``config``); returns the run's plan and the child's one-line description."""
    # in a scratch directory: nothing is written into the run's directory before the check passes
    with tempfile.TemporaryDirectory(prefix="ttl-check-") as scratch:
        path = Path(scratch) / "replayer.config.json"
        plan_path = Path(scratch) / "plan.json"
        path.write_text(json.dumps(config, indent=2))
        res = subprocess.run(
            [
                o.python,
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
        plan = json.loads(plan_path.read_text())
    return plan, res.stdout.strip()
