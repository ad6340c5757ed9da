"""The fitter's command-line options (``python -m stages.fitter``, ``ttl stage fitter``).

They set the stage options of the same names (``StageConfig.options``, the ``[stages.fitter]``
table of a run's configuration), which :class:`stages.fitter.Fitter` reads and checks
(:func:`one_of` for the options with a few choices).
"""

from __future__ import annotations

from ttlcore.errors import ConfigError

#: Adoption modes of ``--adopt``.
ADOPT_MODES = ("ask", "auto", "never")
#: How an extended model is fitted between the window refits of ``--model-update``.
MODEL_UPDATES = ("rolling", "refit")


def one_of(option: str, value: str, choices: tuple[str, ...]) -> str:
    """``value`` of the option ``--<option>`` when it is one of ``choices``; ConfigError otherwise."""
    if value not in choices:
        raise ConfigError(f"fitter --{option}: expected one of {', '.join(choices)}, got {value!r}")
    return value


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
        help="rank the effects not in the model every N segments (default 0: on model changes only)",
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
    }
