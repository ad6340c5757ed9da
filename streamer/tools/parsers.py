"""The options of the operations subcommands of ``ttl`` (run, stage, router, control,
credentials, refit, reprocess, inspect, view), declared without importing what runs them.

Each parser names its handler (``"streamer.tools.cli:_cmd_run"``), imported by
:func:`ttlcore.cli.main.main` only once the arguments have parsed: ``ttl --help`` and an
argument error answer without loading Zenoh, Dask or the science.  Conventions: ``docs/cli.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ttlcore.cli.main import (
    ANALYZE_BAND,
    DIAGNOSE_BAND,
    add_band,
    add_candidates,
    add_json,
    add_model,
    add_out_dir,
    add_quiet,
    add_scheduler,
    add_segment,
    add_truth,
    input_file,
    output_file,
    positive_int,
)
from ttlcore.cli.simulation_options import duration

from ..bus.security import ROLES
from ..bus.topology import STAGES

#: memory limit per local Dask worker (``ttlcore.app.reprocessing.DEFAULT_MEMORY_LIMIT``)
DEFAULT_MEMORY_LIMIT = "6GiB"


def _file_not_stdout(text: str) -> str:
    """A file to write that cannot be standard output (HDF5)."""
    if text == "-":
        raise argparse.ArgumentTypeError("an HDF5 file name, not '-'")
    return output_file(text)


def register(sub) -> None:
    """Add the operations subcommands to the ``ttl`` subparsers ``sub``."""
    _add_run(sub)
    _add_stage(sub)
    _add_router(sub)
    _add_control(sub)
    _add_credentials(sub)
    _add_refit(sub)
    _add_reprocess(sub)
    _add_inspect(sub)
    _add_view(sub)


# ---------------------------------------------------------------------------- ttl run


def _add_run(sub) -> None:
    p = sub.add_parser(
        "run",
        help=f"run the streaming pipeline ({', '.join(STAGES)})",
        description="Start the five stages as separate processes on a loopback Zenoh (a router process on "
        "127.0.0.1, the stages as its clients, all with mutual TLS), show progress, supervise "
        "them, and stop them once every stage has handled every segment. Recordings go to "
        "RECORDINGS/RUN_ID/<stage>.mcap. Exit status 0 when the run completed.",
    )
    p.add_argument(
        "--config",
        type=Path,
        help="run configuration (JSON or TOML) with these options as keys "
        "(run_id, telemetry, simulate, segment, ...) and 'stages': {name: {option: value}}; "
        "command-line options override it",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--telemetry", nargs="+", metavar="FILE", type=input_file, help="telemetry files (ours or lisainstrument's)"
    )
    src.add_argument(
        "--simulate",
        metavar="OPTIONS",
        help="simulate on the fly with 'ttl simulate' options, e.g. \"--duration 12h --orbit unequal --seed 1\"",
    )
    p.add_argument("--run-id", help="run identifier (letters, digits, '.', '_', '-')")
    p.add_argument("--segment", type=duration, help="segment length, e.g. 1h, 30min or seconds (default 1h)")
    p.add_argument("--recordings", type=Path, help="recordings directory (default recordings)")
    p.add_argument("--pace", type=float, help="replay at X times real time (default: as fast as the stages go)")
    p.add_argument("--window", type=int, help="segments the replay may run ahead of the slowest stage (default 4)")
    p.add_argument(
        "--cache",
        type=int,
        help="segments each stage keeps per output for late joiners and restarted stages (default window + 4)",
    )
    p.add_argument("--skip", action="append", metavar="STAGE", help="do not run STAGE (repeatable)")
    p.add_argument(
        "--external",
        action="append",
        metavar="STAGE",
        help="STAGE runs elsewhere ('ttl stage'): expect it, do not start it (repeatable)",
    )
    p.add_argument(
        "--restart",
        type=int,
        help="restart a stage that dies, up to N times per stage, and the Zenoh router up to N times (default 0)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        default=None,
        help="go on with a run whose launcher died (same options, same --run-id and --recordings): "
        "from the first segment some stage had not handled (RECORDINGS/RUN_ID/board.json)",
    )
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="router endpoint (default tls/127.0.0.1:<free port>; repeatable)",
    )
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5) of the router")
    _add_security(
        p,
        "credentials directory (CA and one certificate per stage, 'ttl credentials'); default "
        "RECORDINGS/RUN_ID/credentials, made on first use. Every session talks mutual TLS and the "
        "router enforces who may publish what",
        "no TLS and no access control (plain TCP on loopback): any local process may publish into the run",
    )
    _add_run_fitter_options(p)
    p.add_argument("--timeout", type=float, help="give up after this many seconds")
    p.add_argument("--log-level", help="log level of the stages (default INFO)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(handler="streamer.tools.cli:_cmd_run")


def _add_run_fitter_options(p) -> None:
    """``ttl run``'s options for the fitter: its FFT segment, window and band, the model and
    what the live diagnosis may do with it."""
    p.add_argument("--fit-segment", type=duration, help="fitter: FFT segment length (default: the segment length)")
    p.add_argument("--fit-window", type=duration, help="fitter: rolling window length (default 1d)")
    add_band(p, ANALYZE_BAND, "fitter: fit band")
    p.add_argument(
        "--effects",
        help="fitter: the model, effect specs and their options comma-separated, as ttl diagnose "
        "--effects (default linear-ttl; any effect ttl diagnose can fit; docs/cli.md, Effect specs)",
    )
    p.add_argument(
        "--effect-module",
        action="append",
        metavar="PATH",
        help="fitter: plugin module or .py file defining effects (repeatable)",
    )
    p.add_argument(
        "--adopt",
        choices=("ask", "auto", "never"),
        help="fitter: what to do with the live diagnosis' recommendation: ask (default: recommend, with "
        "the ttl control command that applies it), auto (adopt what explains the excess), never "
        "(no live diagnosis)",
    )
    p.add_argument(
        "--diagnose-every",
        type=int,
        metavar="N",
        help="fitter: diagnose the window every N segments (default 24; the first time at N/2 when that is 6 or more), after every model change, on a sustained excess and on the last segment",
    )
    p.add_argument(
        "--model-update",
        choices=("rolling", "refit"),
        help="fitter: an extended model between its window refits (every 24 segments and on a model "
        "change): rolling (default: the rolling fit with the model's columns) or refit (the "
        "window refitted every segment, as ttl refit)",
    )
    p.add_argument(
        "--diagnosis-workers",
        type=int,
        metavar="N",
        help="fitter: threads scoring the live diagnosis' candidates (default 1: the fitter shares the "
        "cores with the other stages; the result does not depend on it)",
    )


# ---------------------------------------------------------------------------- ttl stage


def _add_stage(sub) -> None:
    p = sub.add_parser(
        "stage",
        help="run one stage process (for stages on several hosts)",
        description="Run one stage of the pipeline in this process; the options after NAME go "
        "to the stage (see 'ttl stage NAME --help'), e.g. "
        "'ttl stage fitter --run r1 --connect tcp/127.0.0.1:7447'.",
        add_help=True,
    )
    p.add_argument("name", choices=STAGES, metavar="NAME", help=f"one of {', '.join(STAGES)}")
    p.add_argument("args", nargs=argparse.REMAINDER, help="stage options")
    p.set_defaults(handler="streamer.tools.cli:_cmd_stage")


# ---------------------------------------------------------------------------- ttl control


def _add_control(sub) -> None:
    p = sub.add_parser(
        "control",
        help="send a command to a stage of a running pipeline",
        description="Publish ttl/<run>/control/<stage>/<command> (for example the fitter's model: "
        "ttl control --run day3 --connect tcp/127.0.0.1:PORT fitter model "
        '\'{"effects": ["linear-ttl", "drift"]}\') '
        "and wait up to --wait seconds for the stage's "
        "verdict. Exit status 0: accepted (recorded, in force from the next segment); 2: rejected "
        "(the reason is printed), no answer, or no router there (the run has ended: ttl refit works "
        "offline) or one that refuses the credentials; 3: queued by a stage busy inside a segment "
        "(the fitter's diagnosis), which handles it after that segment, a restarted one too.",
    )
    p.add_argument("stage", help="stage name")
    # not dest "command": that is the subcommand's name (the "ttl control:" of its messages)
    p.add_argument("stage_command", metavar="command", help="command (fitter: model; every stage: stop)")
    p.add_argument("payload", nargs="?", default="", help="the message (JSON)")
    p.add_argument("--run", required=True, help="run id")
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        required=True,
        help="the run's router (ttl run prints it), e.g. tcp/127.0.0.1:7447",
    )
    p.add_argument(
        "--credentials",
        type=Path,
        metavar="DIR",
        help="credentials directory of the run (RECORDINGS/RUN/credentials by default for ttl run): "
        "connect with mutual TLS as the 'control' identity (endpoints tls/...)",
    )
    p.add_argument(
        "--wait",
        type=float,
        default=10.0,
        help="seconds to wait for the stage's verdict (default 10; a stage answers between segments, "
        "a busy fitter says 'queued' at once)",
    )
    add_quiet(p, "no status line (the sent command is not confirmed on standard output)")
    p.set_defaults(handler="streamer.tools.cli:_cmd_control")


# ---------------------------------------------------------------------------- ttl credentials


def _add_credentials(sub) -> None:
    p = sub.add_parser(
        "credentials",
        help="make the TLS credentials of a deployment (CA, one certificate per role)",
        description="Create what is missing in DIR: a certificate authority (ca.pem, ca.key) and one "
        f"certificate and key per role ({', '.join(ROLES)}), keys mode 0600. The router certificate names "
        "127.0.0.1, localhost and every --host. Copy ca.pem and a role's .pem/.key to the "
        "host that runs it; keep ca.key where certificates are issued.",
    )
    p.add_argument("directory", type=Path, metavar="DIR")
    p.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="ADDRESS",
        help="address (IP or DNS name) a router listens on for other hosts (repeatable)",
    )
    add_quiet(p, "no status line (nothing printed but errors)")
    p.set_defaults(handler="streamer.tools.cli:_cmd_credentials")


# ---------------------------------------------------------------------------- ttl router


def _add_router(sub) -> None:
    p = sub.add_parser(
        "router",
        help="open a Zenoh router (stages on several hosts)",
        description="Open a Zenoh router and keep it open until interrupted. With --credentials DIR: "
        "mutual TLS, listening on tls/127.0.0.1:7447 only by default, the pipeline's "
        "access-control list enforced, refusals logged on stderr. Multicast scouting off.",
    )
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers to connect to (repeatable)")
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5); --listen/--connect override it")
    _add_security(
        p,
        "credentials directory (ttl credentials): mutual TLS with DIR/router.pem, tls/ endpoints only "
        "(default tls/127.0.0.1:7447), and the access-control list of the pipeline; refused peers and "
        "publications are logged on stderr",
        "plain TCP, no authentication, no access control (default tcp/127.0.0.1:7447)",
    )
    add_quiet(p, "no status lines (listening, closing); the router log stays")
    p.set_defaults(handler="streamer.tools.cli:_cmd_router")


def _add_security(p, credentials_help: str, insecure_help: str) -> None:
    """``--credentials DIR`` and ``--insecure`` (see :mod:`streamer.bus.security`)."""
    p.add_argument("--credentials", type=Path, metavar="DIR", help=credentials_help)
    p.add_argument("--insecure", action="store_true", help=insecure_help)


# ---------------------------------------------------------------------------- ttl refit


def _add_refit(sub) -> None:
    p = sub.add_parser(
        "refit",
        help="refit the recorded segments of a run with another model",
        description="Refit recordings/<run> (its MCAP files alone) with the model given by --effects "
        "and compare with the baseline model under the instrument noise model.",
    )
    p.add_argument("run_dir", metavar="recordings/NAME", help="run directory")
    add_model(p, required=True)
    p.add_argument("--baseline", default="linear-ttl", help="the model to compare with (default linear-ttl)")
    p.add_argument("--segments", metavar="A:B", help="segment indices to refit (default all, contiguous)")
    p.add_argument(
        "--source",
        choices=("auto", "telemetry", "tdi"),
        default="auto",
        help="refit from the recorded telemetry (every effect) or the TDI outputs (default: telemetry when recorded)",
    )
    add_band(p, DIAGNOSE_BAND)
    add_json(p, "the report")
    p.add_argument(
        "--residual",
        type=_file_not_stdout,
        metavar="FILE.h5",
        help="also write the whole model's residual (X2, Y2, Z2 on the telemetry's samples, and each "
        "effect's contribution) to an HDF5 file",
    )
    add_quiet(p)
    p.set_defaults(handler="streamer.tools.refit:_cmd_refit")


# ---------------------------------------------------------------------------- ttl reprocess


def _add_reprocess(sub) -> None:
    p = sub.add_parser(
        "reprocess",
        help="analyse and diagnose many days in parallel on Dask (a local cluster or any scheduler)",
        description="Analysis (ttl analyze) and diagnosis (ttl diagnose) of many telemetry files, or of the days "
        "of a recorded run, in parallel on Dask distributed: a LocalCluster on 127.0.0.1 by default, or the "
        "cluster of --scheduler. Writes DIR/<day>/fit.json (+ figures), DIR/<day>/diagnosis.json, "
        "DIR/summary.json and DIR/summary.md (coefficients per day with sigmas, chi2/dof, recommendations, "
        "steps and drifts across days). Every file is checked before any work: a file that is not telemetry "
        "is refused, the truth files ttl simulate writes beside the days (day.truth.h5) are skipped. A day "
        "that fails is reported (one line) and the exit status is 1; only transient errors (OSError, "
        "MemoryError) are retried. See docs/reprocessing.md.",
    )
    p.add_argument(
        "days",
        nargs="*",
        metavar="DAY",
        help="telemetry files (ours or lisainstrument's), one per day; truth files among them are skipped",
    )
    p.add_argument(
        "--from-recordings",
        metavar="RUN",
        default=None,
        help="a recorded run (recordings/<run>): its telemetry segments reassembled into days",
    )
    p.add_argument(
        "--day-length", default="1d", type=duration, help="length of a day cut from --from-recordings (default 1d)"
    )
    add_out_dir(p)
    add_model(p, "the diagnosis model")
    add_candidates(p)
    add_band(p, ANALYZE_BAND, "band of the fit (ttl analyze's)")
    # the noise model the diagnosis tests against lacks TDI's residual laser noise above 0.8 Hz
    add_band(p, DIAGNOSE_BAND, "band of the diagnosis (ttl diagnose's)", "--diagnose-band")
    add_segment(
        p,
        "FFT segment length of the fit and the diagnosis, e.g. 6h or 15min (default that of "
        "ttl analyze, 6 h, and of ttl diagnose; give a shorter one for days shorter than 6 h)",
    )
    p.add_argument(
        "--truth-beside",
        action="store_true",
        help="compare with the truth file beside each day file when there is one (day.truth.h5)",
    )
    p.add_argument("--no-diagnosis", action="store_true", help="analysis only")
    p.add_argument("--no-witnesses", action="store_true", help="skip the diagnosis' witness search")
    p.add_argument("--no-figures", action="store_true", help="skip the figures of the analysis")
    add_scheduler(p, "a LocalCluster on 127.0.0.1")
    p.add_argument("--workers", type=positive_int, default=2, help="worker processes of the LocalCluster (default 2)")
    p.add_argument(
        "--memory-limit",
        default=DEFAULT_MEMORY_LIMIT,
        help=f"memory limit per local worker (default {DEFAULT_MEMORY_LIMIT})",
    )
    p.add_argument("--dashboard", action="store_true", help="serve the Dask dashboard on 127.0.0.1 (LocalCluster)")
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        help="runs again of a day that failed with a transient error (OSError, MemoryError; default 2); "
        "an error of the data or the options is not retried, a day whose worker died is rescheduled by Dask",
    )
    add_json(p, "the summary (as DIR/summary.json)")
    add_quiet(p, "no progress display, no status lines, no report: errors only (the result is DIR/summary.*)")
    p.set_defaults(handler="streamer.tools.reprocess:run")


# ---------------------------------------------------------------------------- ttl inspect, ttl view


def _add_inspect(sub) -> None:
    p = sub.add_parser(
        "inspect",
        help="summarise a run from its MCAP recordings",
        description="Which stages ran, the segments each produced and received (missing, "
        "duplicates), coefficient trends with uncertainties, the monitor's alerts, "
        "errors, and interruptions (killed or restarted stages), from "
        "recordings/<run>/*.mcap alone.",
    )
    p.add_argument("run_dir", metavar="recordings/NAME", help="run directory")
    add_json(p, "the report")
    add_truth(p, "a simulation's truth file: show the true coefficients over the last fit window")
    add_quiet(p, "accepted for uniformity (inspect shows no progress)")
    p.set_defaults(handler="streamer.tools.inspect:_cmd_inspect")


def _add_view(sub) -> None:
    p = sub.add_parser(
        "view",
        help="open a run's monitor.rrd in the Rerun viewer (bound to 127.0.0.1)",
        description="Open recordings/<run>/monitor.rrd (or an .rrd file) in the rerun viewer "
        "binary, its server bound to 127.0.0.1 only.",
    )
    p.add_argument("run_dir", metavar="recordings/NAME", help="run directory or .rrd file")
    p.add_argument(
        "--web",
        action="store_true",
        help="serve the web viewer on 127.0.0.1 instead (no display needed) and print its URL",
    )
    p.add_argument("--port", type=int, help="with --web: the web viewer's HTTP port (default: a free one)")
    p.add_argument("--print", action="store_true", help="only print the viewer command (not with --web)")
    add_quiet(p, "accepted for uniformity (view shows no progress)")
    p.set_defaults(handler="streamer.tools.inspect:_cmd_view")
