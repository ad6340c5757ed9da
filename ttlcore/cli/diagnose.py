"""``ttl diagnose``: the model against the measurement, from the command line.

::

    ttl diagnose DATA.h5 [--effects linear-ttl,...] [--effect-module PATH] --json OUT [--out DIR]

Prints the one-minute report (:func:`ttlcore.diagnose.diagnoser.text_report`), writes the JSON report
(schema in ``docs/diagnostics.md``) and, with ``--out``, the figures ``residual_vs_noise.png``
and ``witness_coherence.png``.  Never reads a truth file unless ``--truth`` names one, and
then only to add coefficient errors.
"""

from __future__ import annotations

from pathlib import Path

from ..conventions import parse_duration
from ..diagnose.adequacy import FIXED_MODEL_TOLERANCE
from ..diagnose.diagnoser import (
    DiagnoseSettings,
    diagnose,
    fine_band_table,
    strip_internals,
    text_report,
)
from ..diagnose.effects import available_effects, make_effects
from ..diagnose.fitting import fit_model
from ..errors import TTLError
from ..estimate.analyze import check_band, load_truth
from ..io.atomic import write_json
from ..io.reader import file_kind, read_telemetry
from ..plots.diagnosis import plot_residual_vs_noise, plot_witness_coherence
from ..plots.transients import plot_time_frequency
from .progress import status_line


def add_parser(sub) -> None:
    p = sub.add_parser(
        "diagnose",
        help="test the TTL model against the data: where it fails, which effect is missing, how to add it",
        description="Fit a model (a list of effects) under the instrument noise model, test the residual per band "
        "and per time slice, rank every effect not in the model (named effects, entry points, --effect-module) and "
        "a library of generic witnesses. With --effects linear-ttl,EFFECT the linear-only model is shown beside it. "
        "Works on our telemetry and on lisainstrument files. See docs/diagnostics.md.",
    )
    p.add_argument("data", help="telemetry file (ours or a lisainstrument measurement file)")
    p.add_argument("--effects", default="linear-ttl", metavar="EFFECT[:opt=v],...",
                   help="the model: comma-separated effects, options after ':' separated by ';' "
                   "(e.g. linear-ttl,drift,step:t_step=50400;mosas=12+13); default linear-ttl")
    p.add_argument("--effect-module", action="append", default=[], metavar="PATH",
                   help="Python file (or importable module) defining user effects; repeatable")
    p.add_argument("--candidates", default=None, metavar="EFFECT,...", help="named effects and plugins to try (default: all available); the witness effects and "
                   "frequency-dependent couplings of the top witnesses are tried as well")
    p.add_argument("--truth", default=None, help="truth file (or the lisainstrument file itself): adds coefficient errors only")
    p.add_argument("--band", nargs=2, metavar=("FMIN", "FMAX"), default=None, help="band in Hz (default 0.003 0.8)")
    p.add_argument("--segment", default=None, help="FFT segment length (default 6 h, or a quarter of shorter data)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="relative tolerance of the noise model (default 0.02; 0.05 with --noise-model fixed)")
    p.add_argument("--noise-model", choices=("fitted", "fixed"), default="fitted",
                   help="secondary-noise levels fitted with the model (default) or fixed at the paper's levels")
    p.add_argument("--no-witnesses", action="store_true", help="skip the witness search")
    p.add_argument("--json", required=True, metavar="OUT", help="JSON report to write")
    p.add_argument("--out", default=None, metavar="DIR", help="directory for the figures (created)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="threads scoring the candidates side by side (default: one per core, at most 4; "
                        "the report does not depend on it)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)


def split_effects(text: str) -> list[str]:
    """``"linear-ttl,step:t_step=5e4;mosas=12"`` -> ``["linear-ttl", "step:t_step=5e4,mosas=12"]``
    (options inside one effect are separated by ';' on the command line)."""
    out = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        out.append(item.replace(";", ","))
    return out


def run(args) -> int:

    data = Path(args.data)
    if not data.exists():
        raise TTLError(f"{data}: no such file")
    json_path = Path(args.json)
    if not json_path.parent.exists():
        raise TTLError(f"--json: directory {json_path.parent} does not exist")
    modules = list(args.effect_module)
    try:
        effects = make_effects(split_effects(args.effects), modules)
    except TTLError as exc:
        raise TTLError(f"--effects: {exc}") from None
    candidates = None
    if args.candidates:
        known = available_effects(modules)
        candidates = [c.strip() for c in args.candidates.split(",") if c.strip()]
        bad = [c for c in candidates if c not in known]
        if bad:
            raise TTLError(f"--candidates: unknown effect(s) {bad}; known: {', '.join(sorted(known))}")
    s = DiagnoseSettings()
    if args.band is not None:

        s.band = check_band(args.band)
    if args.segment is not None:
        s.segment_duration = parse_duration(args.segment, "--segment")
    s.noise_model = args.noise_model
    if s.noise_model == "fixed":
        s.tolerance = FIXED_MODEL_TOLERANCE
    if args.tolerance is not None:
        if not (0 <= args.tolerance < 1):
            raise TTLError(f"--tolerance: expected a fraction in [0, 1), got {args.tolerance}")
        s.tolerance = args.tolerance
    if args.workers is not None:
        if args.workers < 1:
            raise TTLError(f"--workers: expected at least 1, got {args.workers}")
        s.workers = args.workers
    with status_line("ttl diagnose", args.quiet) as say:  # in place on a terminal
        say(f"reading {data}")
        tm = read_telemetry(data)
        truth = None
        if args.truth:
            tr = load_truth(args.truth, tm, file_kind(data), data)
            truth, _ = tr.mean_coefficients(tm.t0, tm.t0 + tm.duration)
        report = diagnose(tm, effects, settings=s, effect_modules=modules, candidates=candidates,
                          truth_coefficients=truth, witnesses=not args.no_witnesses, progress=say)
    internals = report["_internals"]
    report = strip_internals(report)
    report["file"] = str(data)
    report["truth_file"] = str(args.truth) if args.truth else None
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)

        wdata, model = internals["data"], internals["model"]  # not ``data``: the file name, printed below
        fits = {"model": model}
        if "before" in report:
            fits = {"linear-ttl": fit_model(wdata, make_effects(["linear-ttl"]), time_table=False), "model": model}
        fine = {label: fine_band_table(fit) for label, fit in fits.items()}
        paths = {"residual_vs_noise": str(plot_residual_vs_noise(wdata, fits, out / "residual_vs_noise.png", s.tolerance,
                                                                 fine))}
        if report.get("witnesses"):
            paths["witness_coherence"] = str(plot_witness_coherence(report["witnesses"], out / "witness_coherence.png"))
        if internals.get("transient_map") is not None:
            paths["time_frequency"] = str(plot_time_frequency(internals["transient_map"], report["transients"],
                                                              out / "time_frequency.png"))
        report["figures"] = paths
    write_json(json_path, report)
    print(text_report(report, str(data)))
    print(f"  wrote {json_path}" + (", " + ", ".join(report["figures"].values()) if report.get("figures") else ""))
    return 0
