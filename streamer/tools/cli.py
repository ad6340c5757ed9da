"""The operations subcommands of ``ttl``: what runs them (their options are declared in
:mod:`streamer.tools.parsers`; the entry point is :func:`streamer.tools.main.main`).

``ttl run``
    The whole pipeline: five stage processes on a loopback Zenoh, progress, supervision
    (:mod:`streamer.launch.launcher`).
``ttl stage NAME [options]``
    One stage process (``python -m stages.<name>``), e.g. on another host:
    ``ttl stage fitter --run r1 --connect tcp/10.0.0.5:7447``; ``ttl stage NAME --help``.
``ttl router``
    A Zenoh router (for stages on several hosts).
``ttl reprocess``
    Analysis and diagnosis of many days (files or a recorded run) on Dask
    (:mod:`streamer.tools.reprocess`).
``ttl inspect``, ``ttl view``, ``ttl refit``
    Offline inspection of recordings (:mod:`streamer.tools.inspect`, :mod:`streamer.tools.refit`).

Errors print one line naming the option, file or stage at fault and exit non-zero.
"""

from __future__ import annotations

import importlib
import json
import json as _json
import logging
import sys
import tomllib
import uuid
from pathlib import Path
from types import ModuleType

import zenoh

from ttlcore.errors import TTLError

from ..bus.keys import check_name, control_key
from ..bus.reach import listening, zenoh_error_text
from ..bus.security import ROLES, ROUTER_LOG_FILTER, ensure_credentials, filter_log
from ..bus.session import (
    DEFAULT_ROUTER_LISTEN,
    Bus,
    SessionConfigError,
    SessionSettings,
    make_config,
    open_router,
    open_session,
)
from ..bus.topology import stage_module
from ..launch.launcher import RunOptions, run, stage_module_exists
from ..runtime.processes import SignalFlag
from ..runtime.settings import SettingsError
from ..runtime.stage import Stage, stage_main
from .main import main as ttl_main
from .parsers import register  # noqa: F401  (the operations parsers, for build_parser(register))

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- ttl run


def _read_config(path: Path) -> dict:
    try:
        text = path.read_text()
    except OSError as exc:
        raise TTLError(f"--config: {path}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise TTLError(
            f"--config: {path}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'}: {exc}"
        ) from None
    if not isinstance(data, dict):
        raise TTLError(f"--config: {path}: expected an object of options")
    return data


#: ``ttl run`` options (and ``--config`` keys) that go to the fitter: option -> fitter option.
#: Exit status of ``ttl control`` when the stage queued the command (busy inside a segment)
#: and gave no verdict within ``--wait``: it will be handled (0: accepted; 2: rejected).
CONTROL_QUEUED = 3

FITTER_OPTIONS = {
    "fit_segment": "fit_segment",
    "fit_window": "window_duration",
    "band": "band",
    "effects": "effects",
    "effect_module": "effect_modules",
    "adopt": "adopt",
    "diagnose_every": "diagnose_every",
    "model_update": "model_update",
    "diagnosis_workers": "diagnosis_workers",
}


def _split(values) -> tuple:
    out: list[str] = []
    for v in values or ():
        out.extend(x for x in str(v).split(",") if x)
    return tuple(out)


def run_options(args) -> RunOptions:
    """:class:`streamer.launch.launcher.RunOptions` from ``--config`` and the command line."""

    conf = _read_config(args.config) if args.config else {}
    stages, fitter = _config_stages(conf, args.config)
    cli = _command_line_options(args)
    if args.telemetry or args.simulate:  # the command line's source replaces the file's
        conf.pop("telemetry", None)
        conf.pop("simulate", None)
    merged = {**conf, **{k: v for k, v in cli.items() if v is not None}}
    for key, name in FITTER_OPTIONS.items():
        if getattr(args, key) is not None:
            fitter[name] = getattr(args, key)
    if fitter:
        stages = {**stages, "fitter": fitter}
    if not merged.get("run_id"):
        raise TTLError("--run-id is required (or 'run_id' in --config)")
    for key in ("skip", "external", "listen"):  # one name for a list of one
        if isinstance(merged.get(key), str):
            merged[key] = (merged[key],)
    if isinstance(merged.get("telemetry"), str):
        merged["telemetry"] = [merged["telemetry"]]
    try:  # types and values checked (and paths, lists converted) by streamer.runtime.settings
        return RunOptions.from_dict({**merged, "stage_options": stages, "quiet": args.quiet})
    except SettingsError as exc:
        raise TTLError(f"--config: {args.config}: {exc}" if args.config else str(exc)) from None


def _config_stages(conf: dict, path) -> tuple[dict, dict]:
    """The ``stages`` options of a ``--config`` file ``conf`` (taken out of it) and the
    fitter's, with the fitter options given at the top level (:data:`FITTER_OPTIONS`, taken
    out too); a TTLError naming ``path`` for an unknown option or a malformed ``stages``."""
    known = set(RunOptions.__dataclass_fields__) | {"stages", *FITTER_OPTIONS}
    unknown = sorted(set(conf) - known)
    if unknown:
        raise TTLError(f"--config: {path}: unknown option {unknown[0]!r} (known: {', '.join(sorted(known))})")
    stages = conf.pop("stages", {}) or {}
    if not isinstance(stages, dict):
        raise TTLError(f"--config: {path}: 'stages' must map stage names to options")
    fitter = dict(stages.get("fitter") or {})
    for key, name in FITTER_OPTIONS.items():
        if key in conf:
            fitter[name] = conf.pop(key)
    return stages, fitter


def _command_line_options(args) -> dict:
    """The options of ``ttl run``'s command line (None: not given)."""
    cli = {
        "run_id": args.run_id,
        "telemetry": args.telemetry,
        "simulate": args.simulate,
        "segment": args.segment,
        "recordings": args.recordings,
        "pace": args.pace,
        "window": args.window,
        "cache": args.cache,
        "restart": args.restart,
        "zenoh_config": args.zenoh_config,
        "timeout": args.timeout,
        "log_level": args.log_level,
        "credentials": args.credentials,
        "insecure": args.insecure or None,
        "resume": args.resume,
    }
    if args.skip:
        cli["skip"] = _split(args.skip)
    if args.external:
        cli["external"] = _split(args.external)
    if args.listen:
        cli["listen"] = tuple(args.listen)
    return cli


def _cmd_run(args) -> int:

    return run(run_options(args))


# ---------------------------------------------------------------------------- ttl stage


def stage_program(name: str) -> ModuleType:
    """The module ``python -m stages.<name>`` runs: ``stages.<name>``, or the ``__main__``
    of a stage that is a package (``stages/fitter/``: its ``__init__`` imports nothing)."""
    module = importlib.import_module(stage_module(name))
    if hasattr(module, "__path__"):
        module = importlib.import_module(f"{module.__name__}.__main__")
    return module


def _cmd_stage(args) -> int:

    if not stage_module_exists(args.name):
        raise TTLError(f"stage {args.name!r} is not installed (no module {stage_module(args.name)})")
    module = stage_program(args.name)
    if hasattr(module, "main"):
        return int(module.main(args.args) or 0)
    classes = [
        c
        for c in vars(module).values()
        if isinstance(c, type) and issubclass(c, Stage) and c.__module__ == module.__name__
    ]
    if not classes:
        raise TTLError(f"stage {args.name!r}: module {stage_module(args.name)} has neither main() nor a Stage class")
    return int(stage_main(classes[0], args.args) or 0)


# ---------------------------------------------------------------------------- ttl control

#: How long ``ttl control`` tries to open its session once the router's port answers [s]: a
#: router answers a TLS handshake in milliseconds; one it refuses (credentials of another CA)
#: Zenoh retries until then.  (A stage waits :data:`streamer.bus.session.CLIENT_CONNECT_TIMEOUT`.)
CONTROL_CONNECT_TIMEOUT = 5.0


def _control_bus(args) -> Bus:
    """The session of ``ttl control``, or a one-line :class:`TTLError` naming the address and
    the likely cause: no router there (the run has ended), or credentials it refuses."""
    endpoints = tuple(args.connect)
    where = ", ".join(endpoints)
    tls = [e for e in endpoints if e.startswith("tls/")]
    if tls and args.credentials is None:
        raise TTLError(
            f"--connect {tls[0]}: a TLS router needs the run's credentials: give --credentials DIR "
            f"(ttl run makes them in recordings/{args.run}/credentials)"
        )
    settings = SessionSettings(
        mode="client",
        connect=endpoints,
        credentials=args.credentials,
        identity="control" if args.credentials else None,
        connect_timeout=CONTROL_CONNECT_TIMEOUT,
    )
    try:
        make_config(settings)  # the credentials and endpoints checked before anything is reached
    except SessionConfigError as exc:
        raise TTLError(str(exc)) from None
    if all(listening(e) is False for e in endpoints):
        raise TTLError(
            f"no router at {where} (nothing listens there): has the run ended? "
            f"'ttl inspect recordings/{args.run}' says; offline, 'ttl refit recordings/{args.run} --effects ...' "
            "refits its recordings with another model"
        )
    try:
        return Bus.open(settings)
    except Exception as exc:  # zenoh.ZError: "Unable to connect ... Timeout!"
        log.debug("zenoh: %s", zenoh_error_text(exc))
        if args.credentials is not None:
            cause = (
                f"it refused the TLS handshake: the credentials in {args.credentials} are not of the run's CA "
                f"(ttl run's are in recordings/{args.run}/credentials), or it is not the run's router"
            )
        else:
            cause = (
                "it did not answer as a Zenoh router over plain TCP (a run started without --insecure "
                "listens on tls/...: give that endpoint and --credentials DIR)"
            )
        raise TTLError(
            f"cannot connect to the router at {where} within {CONTROL_CONNECT_TIMEOUT:g} s: {cause}"
        ) from None


def _control_verdict(bus: Bus, key: str, args, cid: str) -> dict:
    """Ask ``key`` with the payload (query id ``cid``); the stage's final verdict
    (``accepted``/``rejected``), else its ``queued`` answer, else ``{}`` (no answer within
    ``--wait``)."""
    queued: dict = {}
    for ok, body in bus.ask(key, args.payload.encode(), attachment=cid.encode(), timeout=max(0.1, args.wait)):
        try:
            verdict = _json.loads(body)
        except ValueError:
            continue
        if not ok or not isinstance(verdict, dict) or verdict.get("id") not in (cid, None):
            continue
        if verdict.get("state") in ("accepted", "rejected"):
            return verdict
        if verdict.get("state") == "queued" and not queued:
            queued = verdict
            if not args.quiet:
                print(
                    f"ttl control: {args.stage} queued {args.stage_command} ({verdict.get('message') or ''}); "
                    "waiting for its verdict",
                    flush=True,
                )
    return queued


def _cmd_control(args) -> int:

    key = control_key(
        check_name(args.run, "run id"), check_name(args.stage, "stage"), check_name(args.stage_command, "command")
    )
    if args.payload:
        try:
            _json.loads(args.payload)
        except ValueError as exc:
            raise TTLError(f"payload: not JSON ({exc})") from None
    cid = uuid.uuid4().hex
    with _control_bus(args) as bus:
        if args.stage not in bus.alive_stages(args.run, timeout=1.0):
            raise TTLError(
                f"no stage {args.stage!r} alive in run {args.run!r} (the router at {', '.join(args.connect)} answers)"
            )
        verdict = _control_verdict(bus, key, args, cid)
    state = verdict.get("state")
    if state == "accepted":
        if not args.quiet:
            print(f"ttl control: {args.stage} accepted {args.stage_command} (id {cid})")
        return 0
    if state == "rejected":
        raise TTLError(f"{args.stage} rejected {args.stage_command}: {verdict.get('message') or ''}")
    if state == "queued":
        print(
            f"ttl control: {args.stage} queued {args.stage_command} (id {cid}) and has not handled it within "
            f"{args.wait:g} s: it will (a restarted {args.stage} too); 'ttl inspect' shows the verdict",
            file=sys.stderr,
        )
        return CONTROL_QUEUED
    raise TTLError(
        f"{args.stage} did not answer {args.stage_command} within {args.wait:g} s: busy (it handles the "
        f"command when free, unless it stops first) or stopped; 'ttl inspect' says whether it was "
        f"handled: look before sending it again"
    )


# ---------------------------------------------------------------------------- ttl credentials


def _cmd_credentials(args) -> int:

    d = ensure_credentials(args.directory, hosts=tuple(args.host))
    if not args.quiet:
        print(f"ttl credentials: {d}: ca.pem and {', '.join(ROLES)} (.pem, .key)")
    return 0


# ---------------------------------------------------------------------------- ttl router


def _cmd_router(args) -> int:

    if (args.credentials is None) == (not args.insecure):
        raise TTLError(
            "give --credentials DIR (mutual TLS and access control; 'ttl credentials DIR' makes it) "
            "or --insecure (plain TCP, anyone reaching the port may publish)"
        )
    default: tuple[str, ...] = DEFAULT_ROUTER_LISTEN
    if args.credentials is not None:
        # the router's log (stderr) is the record of refused peers and publications
        filter_log()
        zenoh.init_log_from_env_or(ROUTER_LOG_FILTER)
        default = tuple(e.replace("tcp/", "tls/", 1) for e in DEFAULT_ROUTER_LISTEN)
    listen = tuple(args.listen) if args.listen else (None if args.zenoh_config else default)
    # handlers first: a SIGTERM right after the router starts listening still closes it
    # cleanly; a flag, not a threading.Event: Event.set() in a handler can deadlock on the
    # Event's own lock (streamer.runtime.processes.SignalFlag)
    stop = SignalFlag().install()
    try:
        try:
            if listen is None:  # the file's endpoints
                session = open_session(
                    SessionSettings(
                        mode="router",
                        config_file=args.zenoh_config,
                        connect=tuple(args.connect) if args.connect else None,
                        credentials=args.credentials,
                        identity="router" if args.credentials else None,
                    )
                )
            else:
                session = open_router(
                    listen=listen,
                    connect=tuple(args.connect or ()),
                    config_file=args.zenoh_config,
                    credentials=args.credentials,
                )
        except SessionConfigError as exc:
            raise TTLError(str(exc)) from None
        except Exception as exc:  # zenoh: address in use, bad endpoint
            where = ", ".join(listen) if listen else f"the endpoints of {args.zenoh_config}"
            raise TTLError(f"cannot open the router on {where}: {exc}") from None
        try:
            if not args.quiet:
                print(
                    f"ttl router: zenoh router {session.zid()} listening on "
                    f"{', '.join(listen) if listen else 'the endpoints of ' + str(args.zenoh_config)}; "
                    "Ctrl-C to stop",
                    file=sys.stderr,
                    flush=True,
                )
            while not stop.wait(0.5):
                pass
            if not args.quiet:
                print(f"ttl router: {stop.name}: closing", file=sys.stderr, flush=True)
        finally:
            session.close()
    finally:
        stop.restore()
    return 0


def main(argv=None) -> int:
    """The ``ttl`` command (:func:`streamer.tools.main.main`; kept here for ``python -m streamer.tools.cli``)."""
    return ttl_main(argv)


if __name__ == "__main__":
    sys.exit(main())
