"""``ttl refit``: refit the recorded segments of a run with another model, offline.

The segments come from the run's MCAP files alone: the telemetry the replayer published
(``replayer.mcap``, or the inputs the TDI builder recorded), else the TDI outputs of the
TDI builder (``tdi_builder.mcap``); files of restarted stages (``<stage>.<n>.mcap``) are
merged, one copy per segment index.  With the telemetry every effect is available (the
TDI is recomputed); from TDI outputs alone the model may use ``linear-ttl``, ``drift`` and
``step``.  The refit is :func:`ttlcore.diagnose.diagnoser.refit`: the model and the baseline (default
the linear TTL) fitted under the instrument noise model, side by side: chi^2/dof overall
and per band, delta chi^2 and log Bayes factor of the change, the coefficients.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import h5py

from ttlcore.cli.diagnose import check_step_times
from ttlcore.cli.progress import status_line
from ttlcore.cli.report import to_stdout, write_report
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.diagnoser import DiagnoseSettings, refit
from ttlcore.diagnose.diagnosis import Refit
from ttlcore.diagnose.prediction import fit_residual
from ttlcore.effects import make_effects
from ttlcore.effects import split_effects as split
from ttlcore.errors import TTLError

from ..bus.messages import concatenate_telemetry, tdi_of, telemetry_of
from ..bus.segment_record import segment_meta
from ..bus.topology import PRODUCERS, STAGES, UPSTREAM
from ..recording.recorder import RecordingError, read_recording
from .inspect import InspectError, recording_files

log = logging.getLogger(__name__)


class RefitError(TTLError):
    """A run cannot be refitted (the message names the directory, file or option)."""


def recorded_segments(run_dir, topic: str, stages: tuple[str, ...] | None = None) -> dict[int, tuple]:
    """Index -> ``(header, arrays)`` of the ``topic`` segments recorded in a run directory
    (the first stage of ``stages`` that holds any; every file of that stage merged).  Default
    stages: the topic's producer, then the stages that consume it (:mod:`streamer.bus.topology`)."""
    if stages is None:
        stages = (PRODUCERS[topic], *(s for s in STAGES if UPSTREAM.get(s) == PRODUCERS[topic]))
    files = recording_files(run_dir)
    for stage in stages:
        found: dict[int, tuple] = {}
        for path in files.get(stage, ()):
            try:
                rec = read_recording(path)
            except RecordingError as exc:
                log.warning("%s: skipped (%s)", path, exc)
                continue
            for seg in rec.segments(topic):
                found.setdefault(seg.header.index, (seg.header, seg.arrays))
        if found:
            return found
    return {}


def _select(found: dict[int, tuple], first: int | None, last: int | None) -> list[tuple]:
    lo, hi = min(found), max(found)
    for end in (first, last):  # a range beyond the recordings is refused, not clipped
        if end is not None and not lo <= end <= hi:
            asked = f"{'' if first is None else first}:{'' if last is None else last}"
            raise RefitError(
                f"--segments {asked}: the run recorded segments {lo}-{hi}; "
                f"give a range inside them, or leave an end open ({lo}: or :{hi})"
            )
    idx = sorted(i for i in found if (first is None or i >= first) and (last is None or i <= last))
    if not idx:
        raise RefitError("no recorded segment in the range asked")
    gaps = [i for i in range(idx[0], idx[-1] + 1) if i not in found]
    if gaps:
        raise RefitError(
            f"segments {gaps[:5]}{'...' if len(gaps) > 5 else ''} are missing from the recordings: "
            "refit a contiguous range (--segments A:B)"
        )
    return [found[i] for i in idx]


def load_run(run_dir, segments: tuple[int | None, int | None] = (None, None), source: str = "auto"):
    """The data of a recorded run for a refit: a :class:`Telemetry` (``source="telemetry"``)
    or a list of :class:`~ttlcore.tdi.data.TDIData` segments (``"tdi"``); ``"auto"`` prefers
    telemetry.  Returns ``(data, description, dws_asd)`` (the DWS readout-noise level the
    replayer passed down, None when not recorded)."""
    first, last = segments
    if source in ("auto", "telemetry"):
        found = recorded_segments(run_dir, "telemetry")
        if found:
            parts = [telemetry_of(h, a) for h, a in _select(found, first, last)]
            tm = concatenate_telemetry(parts, source=str(run_dir))
            return (
                tm,
                f"telemetry of {len(parts)} recorded segments ({tm.size / tm.fs / 3600:g} h)",
                segment_meta(found[min(found)][0]).dws_asd,
            )
        if source == "telemetry":
            raise RefitError(f"{run_dir}: no recorded telemetry (replayer.mcap, or tdi_builder.mcap inputs)")
    found = {
        i: (h, a)
        for i, (h, a) in recorded_segments(run_dir, "tdi", stages=(PRODUCERS["tdi"],)).items()
        if "regressors" in a
    }  # a tdi_builder under `ttl run` records X2, Y2, Z2 only
    if not found:
        raise RefitError(
            f"{run_dir}: no recorded telemetry, nor TDI segments with their regressors, to refit "
            "(a tdi_builder records X2, Y2, Z2 only: refit from the replayer's telemetry)"
        )
    tdi = [tdi_of(h, a) for h, a in _select(found, first, last)]
    return (
        tdi,
        f"TDI of {len(tdi)} recorded segments ({sum(p.size / p.fs for p in tdi) / 3600:g} h)",
        segment_meta(found[min(found)][0]).dws_asd,
    )


def refit_settings(dws_asd=None, band=None) -> DiagnoseSettings:
    """The diagnosis settings of a refit of recorded (or live) segments: the DWS readout
    noise the replayer passed down (None: the telemetry's or the paper's) and the band
    (None: the diagnosis default).  The live fitter uses the same, so that its window fits
    equal ``ttl refit``'s."""
    settings = DiagnoseSettings(dws_asd=None if dws_asd is None else float(dws_asd))
    return replace(settings, band=tuple(float(b) for b in band)) if band else settings


@dataclass(frozen=True)
class RunRefit:
    """A recorded run refitted (:func:`refit_run`).

    Attributes
    ----------
    refit : Refit
        The model and the baseline on the run's data (:func:`ttlcore.diagnose.diagnoser.refit`).
    run : str
        The run directory.
    data : str
        What was refitted, in words (``"telemetry of 24 recorded segments (24 h)"``).
    residual : tuple or None
        With ``residual`` asked for: ``(t0, fs, residual (3, n) X2/Y2/Z2, predictions)``
        (:func:`ttlcore.diagnose.prediction.fit_residual`).
    """

    refit: Refit
    run: str
    data: str
    residual: tuple | None = None

    def to_json(self) -> dict:
        """The JSON report of ``ttl refit``: ``model``, ``baseline``, ``change``, ``source``."""
        report = self.refit.to_json()
        report["source"] = {"run": self.run, "data": self.data}
        return report


def refit_run(
    run_dir,
    effects,
    *,
    baseline=("linear-ttl",),
    effect_modules=(),
    segments=(None, None),
    source: str = "auto",
    band=None,
    residual: bool = False,
    progress=None,
) -> RunRefit:
    """Refit a recorded run with ``effects`` against ``baseline`` (see the module docstring).
    With ``residual`` (telemetry only) the result holds the whole model's residual
    (:attr:`RunRefit.residual`): what the live subtractor publishes for the last segment of
    the same window.  ``progress`` (a ``say(message)`` callable)
    hears of each step."""

    say = progress or (lambda msg: None)
    say(f"reading the recorded segments of {run_dir}")
    data, what, dws = load_run(run_dir, segments, source)
    parts = data if isinstance(data, list) else [data]
    check_step_times(
        make_effects(list(effects), list(effect_modules)), parts[0].t0, parts[-1].t0 + parts[-1].size / parts[-1].fs
    )
    dws = None if dws is None else float(dws)
    settings = refit_settings(dws, band)
    say(
        f"refitting the {what} with {','.join(effects)} and {','.join(baseline)}, "
        f"band {settings.band[0]:g}-{settings.band[1]:g} Hz"
    )
    try:
        result = refit(
            data,
            list(effects),
            settings=settings,
            effect_modules=tuple(effect_modules),
            baseline=list(baseline),
            dws_asd=dws,
        )
    except ValueError as exc:
        raise RefitError(str(exc)) from None
    fit = result.fit
    out = None
    if residual:
        if fit.data.context.tm is None:
            raise RefitError("--residual needs the recorded telemetry (the replayer's recording)")
        out = fit_residual(fit)
    return RunRefit(result, run=str(run_dir), data=what, residual=out)


def format_refit(run: RunRefit) -> str:
    """The side-by-side text report of :func:`refit_run`."""
    m, b, c = run.refit.model, run.refit.baseline, run.refit.change

    def fmt(x, spec=".3f"):
        return format(x, spec) if isinstance(x, (int, float)) else "-"

    bands = m.adequacy.bands
    band = f", band {bands[0].f_lo:.3g}-{bands[-1].f_hi:.3g} Hz" if bands else ""
    lines = [
        f"refit of {run.run}: {run.data}{band}",
        f"  model     {','.join(m.effects)}: {m.n_parameters} parameters, chi2/dof {fmt(m.chi2_dof)}",
        f"  baseline  {','.join(b.effects)}: {b.n_parameters} parameters, chi2/dof {fmt(b.chi2_dof)}",
        f"  change    delta chi2 {fmt(c.delta_chi2, '.1f')}, log Bayes factor {fmt(c.log_bayes_factor, '.1f')}",
        "  chi2/dof against the instrument noise model per band:  baseline -> model",
    ]
    for row, before, after in zip(bands, c.bands_before, c.bands_after):
        flag = "  FAILS" if row.fails else ""
        lines.append(f"    {row.f_lo:.3g}-{row.f_hi:.3g} Hz   {fmt(before)} -> {fmt(after)}{flag}")
    lines += [f"  {s}" for s in m.adequacy.summary]
    values, sigma = m.coefficients.values, m.coefficients.sigma
    base_values = b.coefficients.values
    shown = [n for n in COEFFICIENT_NAMES if n in values]
    if shown:
        lines.append("  linear coefficients [mm/rad]: baseline -> model (sigma)")
        for n in shown:
            lines.append(
                f"    {n:<12} {base_values.get(n, float('nan')) * 1e3:+8.4f} -> {values[n] * 1e3:+8.4f} "
                f"({sigma[n] * 1e3:.4f})"
            )
    extra = [n for n in values if n not in COEFFICIENT_NAMES]
    if extra:
        lines.append("  other parameters of the model: value (sigma) [unit]")
        for n in extra:
            scale, unit = parameter_unit(n)
            lines.append(f"    {n:<28} {values[n] * scale:+.4g} ({sigma.get(n, float('nan')) * scale:.2g}) [{unit}]")
    return "\n".join(lines)


#: display unit of the parameters of the named effects, by column-name prefix (the columns'
#: own units in ttlcore.effects, scaled like the coefficients: m/rad shown in mm/rad)
_PARAMETER_UNITS = (
    ("drift.", 1e3, "mm/rad/day"),
    ("step.", 1e3, "mm/rad"),
    ("cross.", 1e3, "mm/rad"),
    ("quad.", 1.0, "m/rad^2"),
)


def parameter_unit(name: str) -> tuple[float, str]:
    """``(scale, unit)`` to print the parameter ``name`` of a refit (value * scale in unit)."""
    for prefix, scale, unit in _PARAMETER_UNITS:
        if name.startswith(prefix):
            return scale, unit
    if name.endswith(".d1"):  # timing offsets and light-travel-time errors: delays
        return 1.0, "s"
    if name.endswith(".d2"):
        return 1.0, "s^2"
    return 1.0, "column unit, docs/diagnostics.md"


def _parse_range(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    a, sep, b = text.partition(":")
    try:
        return (int(a) if a else None, int(b) if b else None) if sep else (int(a), int(a))
    except ValueError:
        raise RefitError(f"--segments: expected A:B (segment indices), got {text!r}") from None


def _cmd_refit(args) -> int:

    # bad input fails in one line before any work starts: the effects, then the run directory
    make_effects(split(args.effects) + split(args.baseline), args.effect_module)
    if not Path(args.run_dir).is_dir():
        raise RefitError(f"{args.run_dir}: no such run directory")
    segments = _parse_range(args.segments)
    try:
        with status_line("ttl refit", args.quiet) as say:  # in place on a terminal
            run = refit_run(
                args.run_dir,
                split(args.effects),
                baseline=split(args.baseline),
                effect_modules=args.effect_module,
                segments=segments,
                source=args.source,
                band=args.band,
                residual=args.residual is not None,
                progress=say,
            )
    except InspectError as exc:
        raise RefitError(str(exc)) from None
    write_report(args.json, run.to_json())
    text = not to_stdout(args.json)  # with --json -, standard output holds the JSON alone
    if text:
        print(format_refit(run))
    if run.residual is not None:
        write_residual(args.residual, *run.residual)
        if text and not args.quiet:
            print(f"wrote {args.residual}")
    return 0


def write_residual(path, t0: float, fs: float, residual, predictions: dict) -> None:
    """The residual file of ``ttl refit --residual``: datasets ``residual`` (3, n) and
    ``predictions/<i>`` (3, n, attribute ``effect``), attributes ``t0`` [s], ``fs`` [Hz],
    ``channels`` (X2, Y2, Z2); written under a temporary name, then renamed."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs.update(t0=t0, fs=fs, channels=["X2", "Y2", "Z2"], units="fractional frequency")
            f["residual"] = residual
            for i, (spec, x) in enumerate(predictions.items()):
                f[f"predictions/{i}"] = x
                f[f"predictions/{i}"].attrs["effect"] = spec
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RefitError(f"--residual {path}: {exc.strerror or exc}") from None
