"""The fitter's options: :class:`FitterOptions`, and its command line (``python -m
stages.fitter``, ``ttl stage fitter``).

The command line sets the stage options of the same names (``StageConfig.options``, the
``[stages.fitter]`` table of a run's configuration, ``ttl run``'s fitter options), which
:class:`stages.fitter.fitter.Fitter` parses once into a :class:`FitterOptions`.
"""

from __future__ import annotations

from dataclasses import dataclass

from streamer.runtime.stage_options import (
    OrderedOptions,
    band_hz,
    duration_s,
    names,
    nonnegative_int,
    one_of,
    option,
    positive_int,
)
from ttlcore.conventions import DAY

__all__ = ["ADOPT_MODES", "MODEL_UPDATES", "FitterOptions", "add_options", "options"]

#: Adoption modes of ``--adopt``.
ADOPT_MODES = ("ask", "auto", "never")
#: How an extended model is fitted between the window refits of ``--model-update``.
MODEL_UPDATES = ("rolling", "refit")


def _effects(value) -> str | tuple[str, ...]:
    """The model: one string in the grammar of ``--effects`` (read by
    :func:`ttlcore.effects.registry.make_effects`), or a list of specs."""
    return value if isinstance(value, str) else tuple(str(e) for e in value)


#: The live diagnosis' candidate threads: one.  The fitter shares the machine's cores with
#: four stages; on a loaded two-core machine (load 1-6.5; not yet measured idle) a second
#: thread bought no wall time, cost 15 % more CPU and 0.25 GB, and kept every candidate's
#: columns to the end of the phase (docs/operations.md, "Where the fitter's memory goes").
DIAGNOSIS_WORKERS = 1


@dataclass(frozen=True)
class FitterOptions(OrderedOptions):
    """The fitter's options (their command-line help in :func:`add_options`)."""

    #: FFT segment length [s] (None: the telemetry segment's length).
    fit_segment: float | None = option(None, duration_s)
    #: Length of the rolling window [s].
    window_duration: float = option(DAY, duration_s)
    #: Fit band [Hz] (None: the fit's default).
    band: tuple[float, float] | None = option(None, band_hz)
    #: The model at start: effect specs.
    effects: str | tuple[str, ...] = option(("linear-ttl",), _effects)
    #: Plugin modules or .py files defining effects.
    effect_modules: tuple[str, ...] = option((), names)
    #: Window refit under the instrument noise model every N segments (0: never).
    adequacy_every: int = option(24, nonnegative_int)
    #: Rank the effects not in the model every N segments in the window refit (0: on model
    #: changes only, and only without the live diagnosis, which ranks them itself).
    candidates_every: int = option(0, nonnegative_int)
    #: Live diagnosis every N segments (0: never).
    diagnose_every: int = option(24, nonnegative_int)
    #: What to do with a recommendation (:data:`ADOPT_MODES`).
    adopt: str = option("ask", one_of(*ADOPT_MODES))
    #: How an extended model is fitted between window refits (:data:`MODEL_UPDATES`).
    model_update: str = option("rolling", one_of(*MODEL_UPDATES))
    #: Threads scoring the candidates of the live diagnosis and the window refit.
    diagnosis_workers: int = option(DIAGNOSIS_WORKERS, positive_int)


def add_options(p) -> None:
    p.add_argument("--fit-segment", help="FFT segment length (default: the telemetry segment length)")
    p.add_argument("--window-duration", help="rolling window length (default 1d)")
    p.add_argument("--band", nargs=2, type=float, metavar=("FMIN", "FMAX"), help="fit band [Hz]")
    p.add_argument("--settle", type=float, help="seconds to collect cached history before choosing the first segment")
    p.add_argument("--gap-timeout", type=float, help="seconds to wait for a missing segment before skipping it")
    p.add_argument(
        "--effects",
        help="the model: effect specs, comma-separated (default linear-ttl; any effect "
        "ttl diagnose can fit, e.g. linear-ttl,witness:source=12.eta,link=23,delay=2)",
    )
    p.add_argument("--effect-module", action="append", help="plugin module or .py file defining effects (repeatable)")
    p.add_argument(
        "--adequacy-every",
        type=int,
        help="refit the window under the instrument noise model every N segments (default 24; 0: never)",
    )
    p.add_argument(
        "--candidates-every",
        type=int,
        help="rank the effects not in the model every N segments (default 0: on model changes only, when "
        "the live diagnosis is off; with it, each diagnosis ranks them)",
    )
    p.add_argument(
        "--diagnose-every",
        type=int,
        help="diagnose the window as ttl diagnose would every N segments (default 24; 0: never)",
    )
    p.add_argument(
        "--adopt",
        choices=ADOPT_MODES,
        help="ask (default): recommend what to add; auto: adopt a recommendation that explains the excess; "
        "never: no live diagnosis",
    )
    p.add_argument(
        "--model-update",
        choices=MODEL_UPDATES,
        help="an extended model between the window refits (every --adequacy-every segments and on a "
        "model change): rolling (default: the rolling fit with the model's columns, the work of one "
        "segment) or refit (the window refitted every segment, as ttl refit)",
    )
    p.add_argument(
        "--diagnosis-workers",
        type=int,
        help=f"threads scoring the live diagnosis' candidates (default {DIAGNOSIS_WORKERS}: the fitter "
        "shares the cores with the other stages; the result does not depend on it)",
    )


def options(args) -> dict:
    return {
        "fit_segment": args.fit_segment,
        "window_duration": args.window_duration,
        "band": args.band,
        "settle": args.settle,
        "gap_timeout": args.gap_timeout,
        "effects": args.effects,
        "effect_modules": args.effect_module,
        "adequacy_every": args.adequacy_every,
        "candidates_every": args.candidates_every,
        "diagnose_every": args.diagnose_every,
        "adopt": args.adopt,
        "model_update": args.model_update,
        "diagnosis_workers": args.diagnosis_workers,
    }
