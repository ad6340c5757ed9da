"""The ``ttl`` entry point (:func:`main`) and its operations subcommands.

:func:`main` builds the science parser of :mod:`ttlcore.cli.main` with :func:`register`
added: the operations layer imports the science, never the reverse.

``ttl run``
    The whole pipeline: five stage processes on a loopback Zenoh, progress, supervision
    (:mod:`streamer.launcher`).
``ttl stage NAME [options]``
    One stage process (``python -m stages.<name>``), e.g. on another host:
    ``ttl stage fitter --run r1 --connect tcp/10.0.0.5:7447``; ``ttl stage NAME --help``.
``ttl router``
    A Zenoh router (for stages on several hosts).
``ttl reprocess``
    Analysis and diagnosis of many days (files or a recorded run) on Dask
    (:mod:`streamer.reprocess`).
``ttl inspect``, ``ttl view``
    Offline inspection of recordings, from :mod:`streamer.inspect` when it is installed.

Errors print one line naming the option, file or stage at fault and exit non-zero.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import json as _json
import logging
import queue
import sys
import tomllib
from pathlib import Path

import zenoh

from ttlcore.cli.main import main as science_main
from ttlcore.errors import TTLError

from . import refit, reprocess
from .keys import ERRORS, check_name, control_key, topic_pattern
from .launcher import RunOptions, run, stage_module_exists
from .processes import SignalFlag
from .security import ROLES, ROUTER_LOG_FILTER, ensure_credentials, filter_log
from .session import (
    DEFAULT_ROUTER_LISTEN,
    Bus,
    SessionConfigError,
    SessionSettings,
    open_router,
    open_session,
)
from .stage import Stage, stage_main
from .topology import STAGES, stage_module

log = logging.getLogger(__name__)


def register(sub) -> None:
    """Add ``run``, ``stage``, ``router``, ``control`` (and ``inspect``/``view`` when available) to ``ttl``."""
    _add_run(sub)
    _add_stage(sub)
    _add_router(sub)
    _add_control(sub)
    _add_credentials(sub)
    refit.register(sub)
    reprocess.add_parser(sub)
    try:
        spec = importlib.util.find_spec("streamer.inspect")
    except (ImportError, ValueError):
        spec = None
    if spec is not None:
        try:
            inspect_cli = importlib.import_module("streamer.inspect")
        except Exception as exc:  # keep the other subcommands usable
            log.warning("streamer.inspect could not be loaded (%s): no 'ttl inspect'/'ttl view'", exc)
        else:
            if hasattr(inspect_cli, "register"):
                inspect_cli.register(sub)


# ---------------------------------------------------------------------------- ttl run

def _add_run(sub) -> None:
    p = sub.add_parser(
        "run", help=f"run the streaming pipeline ({', '.join(STAGES)})",
        description="Start the five stages as separate processes on a loopback Zenoh (a router process on "
                    "127.0.0.1, the stages as its clients, all with mutual TLS), show progress, supervise "
                    "them, and stop them once every stage has handled every segment. Recordings go to "
                    "RECORDINGS/RUN_ID/<stage>.mcap. Exit status 0 when the run completed.")
    p.add_argument("--config", type=Path, help="run configuration (JSON or TOML) with these options as keys "
                   "(run_id, telemetry, simulate, segment, ...) and 'stages': {name: {option: value}}; "
                   "command-line options override it")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--telemetry", nargs="+", metavar="FILE", help="telemetry files (ours or lisainstrument's)")
    src.add_argument("--simulate", metavar="OPTIONS",
                     help="simulate on the fly with 'ttl simulate' options, e.g. \"--duration 12h --orbit unequal --seed 1\"")
    p.add_argument("--run-id", help="run identifier (letters, digits, '.', '_', '-')")
    p.add_argument("--segment", help="segment length, e.g. 1h, 30min or seconds (default 1h)")
    p.add_argument("--recordings", type=Path, help="recordings directory (default recordings)")
    p.add_argument("--pace", type=float, help="replay at X times real time (default: as fast as the stages go)")
    p.add_argument("--window", type=int, help="segments the replay may run ahead of the slowest stage (default 4)")
    p.add_argument("--cache", type=int, help="segments each stage keeps per output for late joiners and "
                   "restarted stages (default window + 4)")
    p.add_argument("--skip", action="append", metavar="STAGE", help="do not run STAGE (repeatable)")
    p.add_argument("--external", action="append", metavar="STAGE",
                   help="STAGE runs elsewhere ('ttl stage'): expect it, do not start it (repeatable)")
    p.add_argument("--restart", type=int, help="restart a stage that dies, up to N times per stage (default 0)")
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="router endpoint (default tls/127.0.0.1:<free port>; repeatable)")
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5) of the router")
    _add_security(p, "credentials directory (CA and one certificate per stage, 'ttl credentials'); default "
                     "RECORDINGS/RUN_ID/credentials, made on first use. Every session talks mutual TLS and the "
                     "router enforces who may publish what",
                  "no TLS and no access control (plain TCP on loopback): any local process may publish into the run")
    p.add_argument("--fit-segment", help="fitter: FFT segment length (default: the segment length)")
    p.add_argument("--fit-window", help="fitter: rolling window length (default 1d)")
    p.add_argument("--band", nargs=2, type=float, metavar=("FMIN", "FMAX"), help="fitter: fit band [Hz]")
    p.add_argument("--timeout", type=float, help="give up after this many seconds")
    p.add_argument("--log-level", help="log level of the stages (default INFO)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=_cmd_run)


def _read_config(path: Path) -> dict:
    try:
        text = path.read_text()
    except OSError as exc:
        raise TTLError(f"--config: {path}: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise TTLError(f"--config: {path}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'}: {exc}") from None
    if not isinstance(data, dict):
        raise TTLError(f"--config: {path}: expected an object of options")
    return data


def _split(values) -> tuple:
    out = []
    for v in values or ():
        out.extend(x for x in str(v).split(",") if x)
    return tuple(out)


def run_options(args) -> "RunOptions":
    """:class:`streamer.launcher.RunOptions` from ``--config`` and the command line."""

    conf = _read_config(args.config) if args.config else {}
    known = set(RunOptions.__dataclass_fields__) | {"stages", "fit_segment", "fit_window", "band"}
    unknown = sorted(set(conf) - known)
    if unknown:
        raise TTLError(f"--config: {args.config}: unknown option {unknown[0]!r} (known: {', '.join(sorted(known))})")
    stages = conf.pop("stages", {}) or {}
    if not isinstance(stages, dict):
        raise TTLError(f"--config: {args.config}: 'stages' must map stage names to options")
    fitter = dict(stages.get("fitter") or {})
    for key, name in (("fit_segment", "fit_segment"), ("fit_window", "window_duration"), ("band", "band")):
        if key in conf:
            fitter[name] = conf.pop(key)
    cli = {"run_id": args.run_id, "telemetry": args.telemetry, "simulate": args.simulate, "segment": args.segment,
           "recordings": args.recordings, "pace": args.pace, "window": args.window, "cache": args.cache,
           "restart": args.restart, "zenoh_config": args.zenoh_config, "timeout": args.timeout,
           "log_level": args.log_level, "credentials": args.credentials,
           "insecure": args.insecure or None}
    if args.skip:
        cli["skip"] = _split(args.skip)
    if args.external:
        cli["external"] = _split(args.external)
    if args.listen:
        cli["listen"] = tuple(args.listen)
    if args.telemetry or args.simulate:  # the command line's source replaces the file's
        conf.pop("telemetry", None)
        conf.pop("simulate", None)
    merged = {**conf, **{k: v for k, v in cli.items() if v is not None}}
    for key, name in (("fit_segment", "fit_segment"), ("fit_window", "window_duration"), ("band", "band")):
        if getattr(args, key) is not None:
            fitter[name] = getattr(args, key)
    if fitter:
        stages = {**stages, "fitter": fitter}
    if not merged.get("run_id"):
        raise TTLError("--run-id is required (or 'run_id' in --config)")
    for key in ("skip", "external", "listen"):
        if key in merged:
            merged[key] = tuple(merged[key]) if not isinstance(merged[key], str) else (merged[key],)
    if isinstance(merged.get("telemetry"), str):
        merged["telemetry"] = [merged["telemetry"]]
    for key in ("recordings", "zenoh_config", "credentials"):
        if merged.get(key) is not None:
            merged[key] = Path(merged[key])
    try:
        return RunOptions(**merged, stage_options=stages, quiet=args.quiet)
    except TypeError as exc:
        raise TTLError(f"--config: {exc}") from None


def _cmd_run(args) -> int:

    return run(run_options(args))


# ---------------------------------------------------------------------------- ttl stage

def _add_stage(sub) -> None:
    p = sub.add_parser("stage", help="run one stage process (for stages on several hosts)",
                       description="Run one stage of the pipeline in this process; the options after NAME go "
                                   "to the stage (see 'ttl stage NAME --help'), e.g. "
                                   "'ttl stage fitter --run r1 --connect tcp/127.0.0.1:7447'.",
                       add_help=True)
    p.add_argument("name", choices=STAGES, metavar="NAME", help=f"one of {', '.join(STAGES)}")
    p.add_argument("args", nargs=argparse.REMAINDER, help="stage options")
    p.set_defaults(func=_cmd_stage)


def _cmd_stage(args) -> int:

    if not stage_module_exists(args.name):
        raise TTLError(f"stage {args.name!r} is not installed (no module {stage_module(args.name)})")
    module = importlib.import_module(stage_module(args.name))
    if hasattr(module, "main"):
        return int(module.main(args.args) or 0)
    classes = [c for c in vars(module).values()
               if isinstance(c, type) and issubclass(c, Stage) and c.__module__ == module.__name__]
    if not classes:
        raise TTLError(f"stage {args.name!r}: module {stage_module(args.name)} has neither main() nor a Stage class")
    return int(stage_main(classes[0], args.args) or 0)


# ---------------------------------------------------------------------------- ttl control

def _add_control(sub) -> None:
    p = sub.add_parser("control", help="send a command to a stage of a running pipeline",
                       description="Publish ttl/<run>/control/<stage>/<command> (for example the fitter's model: "
                                   "ttl control --run day3 --connect tcp/127.0.0.1:PORT fitter model "
                                   "'{\"effects\": [\"linear-ttl\", \"drift\"]}'), then report a rejection the "
                                   "stage publishes on errors within --wait seconds.")
    p.add_argument("stage", help="stage name")
    p.add_argument("command", help="command (fitter: model; every stage: stop)")
    p.add_argument("payload", nargs="?", default="", help="the message (JSON)")
    p.add_argument("--run", required=True, help="run id")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", required=True,
                   help="the run's router (ttl run prints it), e.g. tcp/127.0.0.1:7447")
    p.add_argument("--credentials", type=Path, metavar="DIR",
                   help="credentials directory of the run (RECORDINGS/RUN/credentials by default for ttl run): "
                        "connect with mutual TLS as the 'control' identity (endpoints tls/...)")
    p.add_argument("--wait", type=float, default=10.0,
                   help="seconds to listen for a rejection (default 10; a stage answers between segments)")
    p.set_defaults(func=_cmd_control)


def _cmd_control(args) -> int:


    key = control_key(check_name(args.run, "run id"), check_name(args.stage, "stage"), check_name(args.command, "command"))
    if args.payload:
        try:
            _json.loads(args.payload)
        except ValueError as exc:
            raise TTLError(f"payload: not JSON ({exc})") from None
    rejections: queue.Queue = queue.Queue()
    try:
        bus = Bus.open(SessionSettings(mode="client", connect=tuple(args.connect), credentials=args.credentials,
                                       identity="control" if args.credentials else None))
    except Exception as exc:
        raise TTLError(f"cannot reach the run's router at {', '.join(args.connect)}: {exc}") from None
    with bus:
        def on_error(sample):
            try:
                err = _json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            if err.get("key") == key:
                rejections.put(err)

        bus.subscriber(topic_pattern(args.run, ERRORS), on_error)
        if args.stage not in bus.alive_stages(args.run, timeout=1.0):
            raise TTLError(f"no stage {args.stage!r} alive in run {args.run!r}")
        bus.session.put(key, args.payload.encode())
        try:
            err = rejections.get(timeout=max(0.0, args.wait))
        except queue.Empty:
            print(f"ttl control: sent {key}; no rejection within {args.wait:g} s")
            return 0
    raise TTLError(f"{args.stage} rejected {args.command}: {err.get('message')}")


# ---------------------------------------------------------------------------- ttl credentials

def _add_credentials(sub) -> None:
    p = sub.add_parser("credentials", help="make the TLS credentials of a deployment (CA, one certificate per role)",
                       description="Create what is missing in DIR: a certificate authority (ca.pem, ca.key) and one "
                                   f"certificate and key per role ({', '.join(ROLES)}), keys mode 0600. The router certificate names "
                                   "127.0.0.1, localhost and every --host. Copy ca.pem and a role's .pem/.key to the "
                                   "host that runs it; keep ca.key where certificates are issued.")
    p.add_argument("directory", type=Path, metavar="DIR")
    p.add_argument("--host", action="append", default=[], metavar="ADDRESS",
                   help="address (IP or DNS name) a router listens on for other hosts (repeatable)")
    p.set_defaults(func=_cmd_credentials)


def _cmd_credentials(args) -> int:

    d = ensure_credentials(args.directory, hosts=tuple(args.host))
    print(f"ttl credentials: {d}: ca.pem and {', '.join(ROLES)} (.pem, .key)")
    return 0


# ---------------------------------------------------------------------------- ttl router

def _add_router(sub) -> None:
    p = sub.add_parser("router", help="open a Zenoh router (stages on several hosts)",
                       description="Open a Zenoh router and keep it open until interrupted. With --credentials DIR: "
                                   "mutual TLS, listening on tls/127.0.0.1:7447 only by default, the pipeline's "
                                   "access-control list enforced, refusals logged on stderr. Multicast scouting off.")
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers to connect to (repeatable)")
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5); --listen/--connect override it")
    _add_security(p, "credentials directory (ttl credentials): mutual TLS with DIR/router.pem, tls/ endpoints only "
                     "(default tls/127.0.0.1:7447), and the access-control list of the pipeline; refused peers and "
                     "publications are logged on stderr",
                  "plain TCP, no authentication, no access control (default tcp/127.0.0.1:7447)")
    p.set_defaults(func=_cmd_router)


def _add_security(p, credentials_help: str, insecure_help: str) -> None:
    """``--credentials DIR`` and ``--insecure`` (see :mod:`streamer.security`)."""
    p.add_argument("--credentials", type=Path, metavar="DIR", help=credentials_help)
    p.add_argument("--insecure", action="store_true", help=insecure_help)


def _cmd_router(args) -> int:

    if (args.credentials is None) == (not args.insecure):
        raise TTLError("give --credentials DIR (mutual TLS and access control; 'ttl credentials DIR' makes it) "
                       "or --insecure (plain TCP, anyone reaching the port may publish)")
    default = DEFAULT_ROUTER_LISTEN
    if args.credentials is not None:


        # the router's log (stderr) is the record of refused peers and publications
        filter_log()
        zenoh.init_log_from_env_or(ROUTER_LOG_FILTER)
        default = tuple(e.replace("tcp/", "tls/", 1) for e in DEFAULT_ROUTER_LISTEN)
    listen = tuple(args.listen) if args.listen else (None if args.zenoh_config else default)
    # handlers first: a SIGTERM right after the router starts listening still closes it
    # cleanly; a flag, not a threading.Event: Event.set() in a handler can deadlock on the
    # Event's own lock (streamer.processes.SignalFlag)
    stop = SignalFlag().install()
    try:
        try:
            if listen is None:  # the file's endpoints
                session = open_session(SessionSettings(mode="router", config_file=args.zenoh_config,
                                                       connect=tuple(args.connect) if args.connect else None,
                                                       credentials=args.credentials,
                                                       identity="router" if args.credentials else None))
            else:
                session = open_router(listen=listen, connect=tuple(args.connect or ()), config_file=args.zenoh_config,
                                      credentials=args.credentials)
        except SessionConfigError as exc:
            raise TTLError(str(exc)) from None
        except Exception as exc:  # zenoh: address in use, bad endpoint
            where = ", ".join(listen) if listen else f"the endpoints of {args.zenoh_config}"
            raise TTLError(f"cannot open the router on {where}: {exc}") from None
        try:
            print(f"ttl router: zenoh router {session.zid()} listening on "
                  f"{', '.join(listen) if listen else 'the endpoints of ' + str(args.zenoh_config)}; Ctrl-C to stop",
                  file=sys.stderr, flush=True)
            while not stop.wait(0.5):
                pass
            print(f"ttl router: {stop.name}: closing", file=sys.stderr, flush=True)
        finally:
            session.close()
    finally:
        stop.restore()
    return 0


def main(argv=None) -> int:
    """The ``ttl`` command: science subcommands (:mod:`ttlcore.cli`) and these."""
    return science_main(argv, registrars=(register,))


if __name__ == "__main__":
    sys.exit(main())
