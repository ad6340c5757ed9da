"""``ttl diagnose``: the model against the measurement, from the command line.

::

    ttl diagnose DATA.h5 [--effects linear-ttl,...] [--effect-module PATH] [--json FILE|-] [--out DIR]

Prints the one-minute report (:meth:`ttlcore.diagnose.diagnosis.Diagnosis.text`), writes the JSON report
(schema in ``docs/diagnostics.md``; ``-``: to standard output instead of the text) and, with
``--out``, the figures ``residual_vs_noise.png`` and ``witness_coherence.png``.  The options are
declared in :mod:`ttlcore.cli.main`, which checks the output paths before any work.  Never reads a truth file unless ``--truth`` names one, and
then only to add coefficient errors.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ..app.analysis import check_band, load_truth
from ..conventions import format_time, parse_duration
from ..diagnose.adequacy import FIXED_MODEL_TOLERANCE
from ..diagnose.diagnoser import DiagnoseSettings, diagnose, fine_band_table
from ..diagnose.diagnosis import Diagnosis
from ..diagnose.fitting import fit_model
from ..effects.registry import available_effects, make_effects, split_effects
from ..errors import TTLError
from ..io.reader import file_kind, read_telemetry
from ..plots.diagnosis import plot_residual_vs_noise, plot_witness_coherence
from ..plots.transients import plot_time_frequency
from .progress import status_line
from .report import to_stdout, write_report


def check_step_times(effects, t_start: float, t_stop: float, option: str = "--effects") -> None:
    """Refuse a step whose time ``t_step`` lies outside the data [s, mission time]: its column
    would be empty, or the linear coupling itself, and the fit would say nothing about it."""
    for effect in effects:
        t = getattr(effect, "options", {}).get("t_step")
        if t is None:  # searched over the data
            continue
        t = float(t)  # seconds (the effect read its unit)
        if not t_start < t < t_stop:
            raise TTLError(
                f"{option}: {effect.name} at t_step={format_time(t)} ({t:g} s) is outside the data "
                f"({t_start:g} - {t_stop:g} s)"
            )


def run(args) -> int:

    data = Path(args.data)
    modules = list(args.effect_module)
    try:
        effects = make_effects(split_effects(args.effects), modules)
    except TTLError as exc:
        raise TTLError(f"--effects: {exc}") from None
    candidates = _candidates(args.candidates, modules)
    s = _settings(args)
    with status_line("ttl diagnose", args.quiet) as say:  # in place on a terminal
        say(f"reading {data}")
        tm = read_telemetry(data)
        check_step_times(effects, tm.t0, tm.t0 + tm.duration)
        truth = None
        if args.truth:
            tr = load_truth(args.truth, tm, file_kind(data), data)
            truth, _ = tr.mean_coefficients(tm.t0, tm.t0 + tm.duration)
        diagnosis = diagnose(
            tm,
            effects,
            settings=s,
            effect_modules=modules,
            candidates=candidates,
            truth_coefficients=truth,
            witnesses=not args.no_witnesses,
            progress=say,
        )
    report = diagnosis.to_json()
    report["file"] = str(data)
    report["truth_file"] = str(args.truth) if args.truth else None
    figures = _figures(diagnosis, Path(args.out), s.tolerance) if args.out else {}
    if args.out:
        report["figures"] = figures
    written = write_report(args.json, report)
    if to_stdout(args.json):
        return 0
    print(diagnosis.text(str(data)))
    files = ([written] if written else []) + list(figures.values())
    if files and not args.quiet:  # a status line; the report above is the result
        print("  wrote " + ", ".join(files))
    return 0


def _candidates(option: str | None, modules: list) -> list[str] | None:
    """The effects of ``--candidates`` (None: every available one); TTLError naming the
    unknown ones."""
    if not option:
        return None
    known = available_effects(modules)
    candidates = [c.strip() for c in option.split(",") if c.strip()]
    bad = [c for c in candidates if c not in known]
    if bad:
        raise TTLError(f"--candidates: unknown effect(s) {bad}; known: {', '.join(sorted(known))}")
    return candidates


def _settings(args) -> DiagnoseSettings:
    """The diagnosis settings, built once from the options (not changed afterwards)."""
    defaults = DiagnoseSettings()
    band = defaults.band if args.band is None else check_band(args.band)
    segment = None if args.segment is None else parse_duration(args.segment, "--segment")
    tolerance = FIXED_MODEL_TOLERANCE if args.noise_model == "fixed" else defaults.tolerance
    if args.tolerance is not None:
        if not (0 <= args.tolerance < 1):
            raise TTLError(f"--tolerance: expected a fraction in [0, 1), got {args.tolerance}")
        tolerance = args.tolerance
    return replace(
        defaults,
        band=band,
        segment_duration=segment,
        noise_model=args.noise_model,
        tolerance=tolerance,
        workers=args.workers,
    )


def _figures(diagnosis: Diagnosis, out: Path, tolerance: float) -> dict[str, str]:
    """The diagnosis' figures drawn into ``out`` (created): the residual against the noise
    (and the linear-only model's, beside a changed model), the witnesses' coherence and the
    time-frequency map of the transients, each where the diagnosis has it; name -> path."""
    out.mkdir(parents=True, exist_ok=True)
    # the whitened data of the fit, not to be confused with ``data``, the file's path
    whitened, model = diagnosis.data, diagnosis.fit
    fits = {"model": model}
    if diagnosis.before is not None:
        fits = {"linear-ttl": fit_model(whitened, make_effects(["linear-ttl"]), time_table=False), "model": model}
    fine = {label: fine_band_table(fit) for label, fit in fits.items()}
    paths = {
        "residual_vs_noise": str(plot_residual_vs_noise(whitened, fits, out / "residual_vs_noise.png", tolerance, fine))
    }
    if diagnosis.witnesses is not None:
        paths["witness_coherence"] = str(
            plot_witness_coherence(diagnosis.witnesses.to_json(), out / "witness_coherence.png")
        )
    if diagnosis.transient_map is not None and diagnosis.transients is not None:
        paths["time_frequency"] = str(
            plot_time_frequency(diagnosis.transient_map, diagnosis.transients.to_json(), out / "time_frequency.png")
        )
    return paths
