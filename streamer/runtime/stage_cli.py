"""The command line of a stage process: options common to all stages, the configuration they
make (:class:`streamer.runtime.stage_config.StageConfig`), and :func:`stage_main`, a stage program's
entry point."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

from ttlcore.errors import TTLError

from ..bus.keys import check_name
from . import allocator
from .lifecycle import die_with_launcher
from .stage_config import StageConfig
from .stagelog import configure_logging


class _Runs(Protocol):
    def run(self) -> int: ...


class StageProgram(Protocol):
    """What :func:`stage_main` reads of a stage class: :class:`streamer.runtime.stage.Stage` and its
    subclasses are ones.  Named by its shape rather than imported: :mod:`streamer.runtime.stage`
    imports this module, so an import of it here, even for the type checker only, would close
    a circle (tests/test_import_graph.py)."""

    name: str
    default_poll_interval: float

    def __call__(self, config: StageConfig) -> _Runs: ...


# the logger of these lines before the stage was split into parts: log lines unchanged
log = logging.getLogger("streamer.runtime.stage")


def stage_arguments(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """Command-line options common to all stages."""
    p = parser or argparse.ArgumentParser()
    p.add_argument("--config", type=Path, help="stage configuration (JSON, StageConfig fields)")
    p.add_argument("--run", help="run id")
    p.add_argument("--name", help="stage name (default: the stage's)")
    p.add_argument("--connect", action="append", default=None, help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", default=None, help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument(
        "--mode",
        choices=("peer", "client"),
        help="Zenoh mode (default: client when --connect is given without --listen, as behind "
        "the router of `ttl run`; else peer)",
    )
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5)")
    p.add_argument(
        "--credentials",
        type=Path,
        metavar="DIR",
        help="credentials directory: mutual TLS with DIR/<stage>.pem (endpoints tls/...)",
    )
    p.add_argument("--recordings", type=Path, help="recordings directory")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--log-json", action="store_true", help="log JSON lines")
    return p


def config_from_args(args: argparse.Namespace) -> StageConfig:
    """A :class:`StageConfig` from ``--config`` and the options overriding it."""
    d = json.loads(args.config.read_text()) if args.config else {}
    for key, value in (("run", args.run), ("stage", args.name), ("recordings", args.recordings)):
        if value:
            d[key] = str(value)
    z = dict(d.get("zenoh") or {})
    for key, value in (
        ("connect", args.connect),
        ("listen", args.listen),
        ("config_file", args.zenoh_config),
        ("credentials", getattr(args, "credentials", None)),
        ("mode", getattr(args, "mode", None)),
    ):
        if value:
            z[key] = value if isinstance(value, list) else str(value)
    if args.connect and not args.listen and not z.get("mode") and not z.get("config_file"):
        z["mode"] = "client"  # a router routes between its clients, not between peers
    d["zenoh"] = z
    return StageConfig.from_dict(d)


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Options of a stage process that override :class:`StageConfig` fields, besides
    :func:`stage_arguments`."""
    p.add_argument("--cache", type=int, help="segments kept per output topic for late joiners")
    p.add_argument(
        "--history", type=int, help="segments asked from each input topic's publisher cache (default: all it holds)"
    )
    p.add_argument("--no-record-inputs", action="store_true", help="do not record input payloads")
    p.add_argument("--poll-interval", type=float, help="longest wait before checking timers [s]")


def _set_common_options(config: StageConfig, args: argparse.Namespace, default_poll_interval: float) -> None:
    """The options of :func:`add_common_options` given on the command line, into ``config``
    (the poll interval the stage's default unless the command line or the ``--config`` file
    sets it)."""
    if args.cache is not None:
        config.cache = args.cache
    if args.history is not None:
        config.history = args.history
    if args.no_record_inputs:
        config.record_inputs = False
    if args.poll_interval is not None:
        config.poll_interval = args.poll_interval
    elif not (args.config and "poll_interval" in json.loads(args.config.read_text())):
        config.poll_interval = default_poll_interval


def stage_main(
    stage_class: StageProgram,
    argv: Sequence[str] | None = None,
    add_options: Callable[[argparse.ArgumentParser], None] | None = None,
    options: Callable[[argparse.Namespace], dict] | None = None,
    check: Callable[[StageConfig], str] | None = None,
) -> int:
    """Entry point of a stage process.

    Parses :func:`stage_arguments`, :func:`add_common_options` and the stage's own
    (``add_options``; ``options(args)`` returns the stage options they set, overriding the
    ``--config`` file's), sets up logging and runs the stage.  With ``--check`` the options
    are validated by ``check(config)`` (which returns a one-line description) and nothing
    runs.  Errors: one line naming the problem on stderr, exit status 2.
    """
    parser = stage_arguments(
        argparse.ArgumentParser(
            prog=f"ttl stage {stage_class.name}", description=(stage_class.__doc__ or "").split("\n\n")[0]
        )
    )
    add_common_options(parser)
    if check is not None:
        parser.add_argument("--check", action="store_true", help="validate the options and exit")
    if add_options is not None:
        add_options(parser)
    args = parser.parse_args(argv)
    configure_logging(args.log_level, args.log_json)
    # before the stage allocates anything or starts threads: freed multi-megabyte blocks go
    # back to the system (streamer/runtime/allocator.py; docs/operations.md, Measured)
    allocator.configure()
    try:
        if not args.config and not args.run:
            raise ValueError("--run (or --config with a 'run' field) is required")
        config = config_from_args(args)
        _set_common_options(config, args, stage_class.default_poll_interval)
        if options is not None:
            config.options = {**config.options, **{k: v for k, v in options(args).items() if v is not None}}
        config.check()  # the fields set one by one above, checked like the file's
        check_name(config.run, "run id")
        if check is not None and args.check:
            print(check(config))
            return 0
        if config.launcher_pid is not None:
            die_with_launcher()  # streamer.runtime.lifecycle: SIGTERM when the launcher dies
        stage = stage_class(config)
    except Exception as exc:  # noqa: BLE001 - one line, no traceback, for user errors
        print(f"ttl stage {stage_class.name}: error: {exc}", file=sys.stderr)
        return 2
    try:
        return stage.run()
    except (TTLError, OSError, ValueError) as exc:
        log.debug("stage failed", exc_info=True)
        print(f"ttl stage {stage_class.name}: error: {exc}", file=sys.stderr)
        return 2
