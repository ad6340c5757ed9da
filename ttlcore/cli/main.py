"""The ``ttl`` command line: its parser, the science subcommands' options, and the dispatch.

The ``ttl`` entry point is :func:`streamer.tools.main.main`: it builds this parser with the
operations subcommands added (``build_parser(streamer.tools.parsers.register)``), so this package
never imports the operations layer; ``python -m ttlcore.cli`` gives the science commands alone.

This module imports no science: every subcommand's options are declared here (argparse
only), and each names the module that runs it (``handler="ttlcore.cli.simulate:run"``),
imported only once the arguments have parsed.  ``ttl --help`` and an argument error thus
answer in a fraction of a second, and a command imports only what it uses.

The conventions every subcommand follows are in ``docs/cli.md``: one-line errors naming the
option, file or field at fault with exit status 2 (no usage dump, no traceback), output
paths checked before any work, ``--json FILE|-``, ``--out DIR``, ``--quiet``, a quiet exit on
a closed pipe.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from .. import __version__
from ..errors import TTLError
from .simulation_options import add_simulation_options, duration

log = logging.getLogger("ttl")

#: default fit band of ``ttl analyze`` [Hz] (``ttlcore.estimate.fit.DEFAULT_BAND``, which the
#: parser must not import; tests/ttlcore/cli/test_conventions.py checks they agree)
ANALYZE_BAND = (3e-3, 0.9)
#: default band of ``ttl diagnose`` [Hz] (``DiagnoseSettings().band``): the residual is tested
#: against the noise model, which lacks TDI's residual laser noise above 0.8 Hz (docs/cli.md)
DIAGNOSE_BAND = (3e-3, 0.8)
#: the paper's scenarios and variants (``ttlcore.app.scenarios``; checked by the same test)
SCENARIO_CASES = ("static_unequal", "keplerian", "vb", "sgwb", "gb1", "gb2", "mbhb1", "mbhb2", "all", "mbhb2_200mhz")
SCENARIO_VARIANTS = ("paper", "lisainstrument", "coloured")


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are one line, exit status 2:
    ``ttl simulate: error: argument --out: expected one argument (ttl simulate --help)``."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# ---------------------------------------------------------------------------
# argument types: checked at parse time, before any work or heavy import
# ---------------------------------------------------------------------------


def output_file(text: str) -> str:
    """A file to write: ``-`` (standard output) or a path whose directory exists."""
    if text == "-":
        return text
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, expected a file name")
    parent = path.parent
    if not parent.exists():
        raise argparse.ArgumentTypeError(f"directory {parent} does not exist")
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{parent} is not a directory")
    if not os.access(parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"directory {parent} is not writable")
    # the permission bits do not tell everything (root, read-only or special file systems):
    # create and remove a file beside the target, as the atomic write will, before any work
    probe = parent / f".{path.name}.probe{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot write {text}: {exc.strerror}") from None
    probe.unlink(missing_ok=True)
    return text


def output_dir(text: str) -> str:
    """A directory to write into (created by the command): not an existing file, and under a
    directory that exists or can be created."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} exists and is not a directory")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise argparse.ArgumentTypeError(f"{parent} is not a directory")
            if not os.access(parent, os.W_OK) and not path.exists():
                raise argparse.ArgumentTypeError(f"cannot create {text}: {parent} is not writable")
            break
    return text


def input_file(text: str) -> str:
    """A file to read: it must exist and not be a directory."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, expected a file")
    return text


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {value}")
    return value


def frequency(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a frequency in Hz, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive frequency in Hz, got {text}")
    return value


def add_json(p, what: str = "the report", required: bool = False) -> None:
    """``--json FILE|-``, the same in every command."""
    p.add_argument(
        "--json",
        metavar="FILE|-",
        type=output_file,
        required=required,
        help=f"write {what} as JSON to FILE ('-': to standard output, instead of the text)",
    )


def add_quiet(p, what: str = "no progress display, no status lines ('wrote ...'): errors and the report only") -> None:
    p.add_argument("--quiet", action="store_true", help=what)


def add_band(p, default, what: str = "band", option: str = "--band") -> None:
    """``--band FMIN FMAX`` [Hz] (or ``option``), None unless given: the command's ``default`` then."""
    p.add_argument(
        option,
        nargs=2,
        type=frequency,
        metavar=("FMIN", "FMAX"),
        default=None,
        help=f"{what} in Hz (default {default[0]:g} {default[1]:g})",
    )


def add_out_dir(p, what: str = "output directory (created)", required: bool = True) -> None:
    """``--out DIR``, the directory a command writes into, checked before any work."""
    p.add_argument("--out", required=required, default=None, metavar="DIR", type=output_dir, help=what)


def add_truth(p, what: str) -> None:
    """``--truth FILE``, a truth file (or lisainstrument file) used for comparisons only."""
    p.add_argument("--truth", default=None, metavar="TRUTH.h5", type=input_file, help=what)


def add_segment(p, what: str) -> None:
    """``--segment DURATION``, the FFT segment length of a fit (``6h``, ``15min`` or seconds)."""
    p.add_argument("--segment", default=None, type=duration, help=what)


def add_model(p, what: str = "the model", required: bool = False) -> None:
    """``--effects`` and ``--effect-module``: the model to fit (effect specs, docs/cli.md) and
    the plugins defining user effects; the same in ttl diagnose, refit and reprocess.
    Not ``required``: the default model is linear-ttl."""
    p.add_argument(
        "--effects",
        required=required,
        default=None if required else "linear-ttl",
        metavar="EFFECT[:opt=v,...],...",
        help=f"{what}: effects and their options after ':', all separated by ',' (e.g. linear-ttl,drift,"
        "step:t_step=14h,mosas=12+13 or linear-ttl,gate:start=15.2h,stop=15.8h; docs/cli.md, Effect specs)"
        + ("" if required else "; default linear-ttl"),
    )
    p.add_argument(
        "--effect-module",
        action="append",
        default=[],
        metavar="PATH",
        help="Python file (or importable module) defining user effects; repeatable (ttl reprocess: "
        "readable by its workers)",
    )


def add_candidates(p) -> None:
    """``--candidates``: the effects a diagnosis ranks beside the model."""
    p.add_argument(
        "--candidates",
        default=None,
        metavar="EFFECT,...",
        help="named effects and plugins to try (default: all available); the witness effects and "
        "frequency-dependent couplings of the top witnesses are tried as well",
    )


def add_scheduler(p, otherwise: str) -> None:
    """``--scheduler ADDRESS``: a running Dask scheduler to run on; ``otherwise`` says where the
    command runs without it."""
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help=f"a running Dask scheduler (tcp://host:8786, or its --scheduler-file) to run on; default: {otherwise}",
    )


# ---------------------------------------------------------------------------
# the science subcommands
# ---------------------------------------------------------------------------


def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate mission telemetry (eta, DWS, delays) and its truth file",
        description="Simulate LISA telemetry at the eta level with TTL coupling (docs/physics.md). "
        "Writes the telemetry FILE and its truth file beside it (day.h5 -> day.truth.h5).",
    )
    add_simulation_options(p)
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument(
        "--telemetry",
        metavar="FILE",
        type=output_file,
        help="telemetry file to write (HDF5); the truth file goes beside it",
    )
    # before the convention (--out is a directory in every command) this option named the file:
    # still accepted, with a note, so that existing scripts keep working
    out.add_argument("--out", metavar="FILE", type=output_file, help=argparse.SUPPRESS)
    p.add_argument(
        "--truth-noises",
        default="",
        help="noise components to store alone in the truth file, "
        "comma-separated (laser, oms, backlink, telescope, test_mass, dws_phi, dws_eta) or 'all'",
    )
    p.add_argument(
        "--chunk",
        default="3h",
        type=duration,
        help="simulation chunk length (memory bound; the result does not depend on it)",
    )
    add_quiet(p)
    p.set_defaults(handler="ttlcore.cli.simulate:run")


def _add_info(sub) -> None:
    p = sub.add_parser("info", help="summarise a telemetry file (ours or lisainstrument's) or a truth file")
    p.add_argument("file", type=input_file, help="HDF5 file")
    add_json(p, "the summary")
    add_quiet(p, "accepted for uniformity (info shows no progress)")
    p.set_defaults(handler="ttlcore.cli.info:run")


def _add_analyze(sub) -> None:
    p = sub.add_parser(
        "analyze",
        help="fit the TTL coefficients of a telemetry file, subtract them, write fit.json and figures",
        description="Batch analysis of one telemetry file (ours or lisainstrument's): TDI, fit of the 24 TTL "
        "coefficients, subtraction in the time domain. Writes DIR/fit.json, DIR/asd_X.png and "
        "DIR/coefficients.png. The truth (our truth file, or for lisainstrument data the lisainstrument "
        "file itself) is only used for comparisons, never by the fit.",
    )
    p.add_argument("data", type=input_file, help="telemetry file (HDF5: ours or a lisainstrument measurement file)")
    add_truth(
        p,
        "truth file (day.truth.h5), or for lisainstrument data the "
        "lisainstrument file (its static coefficients; no TTL residual then)",
    )
    add_band(p, ANALYZE_BAND)
    p.add_argument("--method", default="gls", choices=("gls", "mcmc"), help="gls (default) | mcmc")
    add_segment(p, "FFT segment length of the fit, e.g. 6h, 1h or seconds (default 21600 s)")
    add_out_dir(p)
    add_json(p, "fit.json")
    add_quiet(p)
    p.set_defaults(handler="ttlcore.cli.analyze:run")


def _add_diagnose(sub) -> None:
    p = sub.add_parser(
        "diagnose",
        help="test the TTL model against the data: where it fails, which effect is missing, how to add it",
        description="Fit a model (a list of effects) under the instrument noise model, test the residual per band "
        "and per time slice, rank every effect not in the model (named effects, entry points, --effect-module) and "
        "a library of generic witnesses. With --effects linear-ttl,EFFECT the linear-only model is shown beside it. "
        "Works on our telemetry and on lisainstrument files. See docs/diagnostics.md.",
    )
    p.add_argument("data", type=input_file, help="telemetry file (ours or a lisainstrument measurement file)")
    add_model(p)
    add_candidates(p)
    add_truth(p, "truth file (or the lisainstrument file itself): adds coefficient errors only")
    add_band(p, DIAGNOSE_BAND)
    add_segment(p, "FFT segment length (default 6 h, or a quarter of shorter data)")
    p.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="relative tolerance of the noise model (default 0.02; 0.05 with --noise-model fixed)",
    )
    p.add_argument(
        "--noise-model",
        choices=("fitted", "fixed"),
        default="fitted",
        help="secondary-noise levels fitted with the model (default) or fixed at the paper's levels",
    )
    p.add_argument("--no-witnesses", action="store_true", help="skip the witness search")
    add_json(p, "the report")
    add_out_dir(p, "directory for the figures (created)", required=False)
    p.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        metavar="N",
        help="threads scoring the candidates side by side (default: one per core, at most 4; "
        "the report does not depend on it)",
    )
    add_quiet(p)
    p.set_defaults(handler="ttlcore.cli.diagnose:run")


def _add_scenarios(sub) -> None:
    p = sub.add_parser(
        "scenarios",
        help="run the paper's scenarios with and without GW signals; write summary.md/json and figures",
        description="The paper's cases (static unequal arms, Keplerian arms, verification binaries, stochastic "
        "background, galactic binaries at two epochs, each merger, all sources, MBHB2 with the band ending at "
        "0.2 Hz), each also without GW on the same noise realisation, for the paper's coefficients and beyond "
        "(lisainstrument's coefficient set, coloured jitter). Writes DIR/summary.json, DIR/summary.md and "
        "DIR/<variant>/<case>_*.png.",
    )
    add_out_dir(p)
    p.add_argument(
        "--cases", default="all-cases", help="comma-separated cases (default all): " + ", ".join(SCENARIO_CASES)
    )
    p.add_argument(
        "--variants",
        default=",".join(SCENARIO_VARIANTS),
        help="comma-separated variants: " + ", ".join(SCENARIO_VARIANTS) + " (default all three)",
    )
    p.add_argument(
        "--duration", default="1d", type=duration, help="length of each case, e.g. 1d or 6h (default 1d, as the paper)"
    )
    p.add_argument("--seed", type=int, default=1, help="noise seed shared by all cases (default 1)")
    p.add_argument("--no-figures", action="store_true", help="skip the figures")
    add_scheduler(p, "this process, or a local cluster of --workers processes")
    p.add_argument(
        "--workers",
        type=int,
        default=0,
        help="run the cases on a local Dask cluster of N worker processes (default 0: in this process)",
    )
    add_quiet(p)
    p.set_defaults(handler="ttlcore.cli.scenarios:run")


def register(sub) -> None:
    """Add the science subcommands (simulate, info, analyze, diagnose, scenarios) to ``sub``."""
    _add_simulate(sub)
    _add_info(sub)
    _add_analyze(sub)
    _add_diagnose(sub)
    _add_scenarios(sub)


# ---------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------


def build_parser(*registrars) -> argparse.ArgumentParser:
    """The ``ttl`` parser: the science subcommands, plus those each of ``registrars`` adds
    (the operations package passes its own: ``ttlcore`` never imports it)."""
    parser = Parser(
        prog="ttl",
        description="Tilt-to-length noise subtraction for LISA. Conventions shared by every command: docs/cli.md.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("--version", action="version", version=f"ttl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=Parser)
    for add in (register, *registrars):
        add(sub)
    return parser


def handler(args):
    """The function that runs the parsed command (``"module:function"``, imported now)."""
    module, _, name = args.handler.partition(":")
    return getattr(importlib.import_module(module), name)


def _quiet_stdout() -> None:
    """After a closed pipe (``ttl info day.h5 | head -1``): send what is left to /dev/null, so
    that the interpreter's final flush does not complain either."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def main(argv=None, registrars=()) -> int:
    """Run one ``ttl`` subcommand; ``registrars`` add subcommands beyond the science ones.

    Exit status: 0 done, 1 the command's own verdict (e.g. failed days), 2 bad arguments or
    input (one line on standard error), 130 interrupted.  A reader that closed the pipe
    (``| head``) ends the command quietly with status 0.
    """
    parser = build_parser(*registrars)
    try:
        args = parser.parse_args(argv)
    except BrokenPipeError:  # ttl --help | head -1
        _quiet_stdout()
        return 0
    except SystemExit as exc:  # --help, --version or an argument error, already printed
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    interrupts: list = []
    try:
        with _interrupts_noted(interrupts):
            return int(handler(args)(args) or 0)
    except BrokenPipeError:
        _quiet_stdout()
        return 0
    except (TTLError, ValueError, OSError) as exc:
        if interrupts:  # Ctrl-C reached the command's helpers first (a Dask worker died of it)
            print(f"ttl {args.command}: interrupted", file=sys.stderr)
            return 130
        print(f"ttl {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ttl {args.command}: interrupted", file=sys.stderr)
        return 130


@contextlib.contextmanager
def _interrupts_noted(interrupts: list):
    """SIGINT noted in ``interrupts`` and raised as KeyboardInterrupt, as Python's default
    handler does: Ctrl-C at a terminal reaches the whole process group at once, and a
    helper process that died of it (a ``ttl reprocess`` worker) could otherwise surface as
    the command's error before the interrupt does (exit 2 instead of 130 on a loaded
    machine).  Only in the main thread, where signal handlers live; the previous handler
    is restored."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is not (
        signal.default_int_handler
    ):
        yield
        return

    def noted(signum, frame):
        interrupts.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, noted)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


if __name__ == "__main__":
    sys.exit(main())
