"""Batch analysis of one telemetry file: TDI, fit, subtraction, ``fit.json`` and figures
(``ttl analyze``).

::

    from ttlcore.app.analysis import analyze
    out = analyze("day.h5", truth_path="day.truth.h5", out_dir="day-analysis")
    out["fit"].coefficients, out["paths"]["fit_json"]

Input: one of our telemetry files or a lisainstrument 2.x measurement file (auto-detected by
:func:`ttlcore.io.reader.read_telemetry`).

Truth (optional, never used by the fit; it only adds comparisons):

- one of our truth files (``day.truth.h5`` beside ``day.h5``): the true coefficients are
  the mean of its ``coefficients`` series over the fit window (the span of the FFT
  segments actually fitted), and its ``ttl`` series gives the TDI of the true TTL, hence
  the TTL residual and the noise without TTL;
- for lisainstrument data, the lisainstrument file itself (``--truth`` = the data file, or
  another lisainstrument file of the same run): the static coefficients of its metadata
  (:func:`ttlcore.io.lisainstrument.lisainstrument_truth`).  lisainstrument files hold
  no TTL series, so the TTL residual and noise-without-TTL curves are skipped and
  ``fit.json`` says so under ``notes``.

Outputs in ``out_dir``: ``fit.json`` (:meth:`ttlcore.estimate.fit.FitResult.to_json` plus the run's
provenance), ``asd_X.png`` and ``coefficients.png`` (:mod:`ttlcore.plots.batch`); all written
atomically (temporary name, then rename).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, C
from ..errors import TelemetryError, TTLError
from ..estimate.fit import DEFAULT_BAND, FitSettings, dws_asd_from_config, fit_tdi, segment_spectra
from ..estimate.mcmc import fit_mcmc
from ..estimate.subtraction import analyse_subtraction
from ..io.atomic import write_json
from ..io.lisainstrument import lisainstrument_truth
from ..io.reader import file_kind, read_telemetry
from ..io.telemetry import read_header
from ..io.truth import read_truth
from ..io.truth import truth_path as default_truth_path
from ..plots.batch import asd_x_curves, plot_asd_x, plot_coefficients
from ..tdi.data import compute_tdi

log = logging.getLogger(__name__)

#: Fit methods ``analyze`` knows.
METHODS = ("gls", "mcmc")
#: Sampling rate the fit works at (``fit.segment_spectra`` decimates to it) [Hz].
FIT_FS = 2.0


def check_band(
    band, fs: float = 4.0, segment_duration: float | None = None, option: str = "--band"
) -> tuple[float, float]:
    """Validate a band ``(fmin, fmax)`` [Hz]; raises :class:`TTLError` naming ``option``."""
    try:
        fmin, fmax = (float(b) for b in band)
    except (TypeError, ValueError):
        raise TTLError(f"{option}: expected two frequencies FMIN FMAX in Hz, got {band!r}") from None
    if not (math.isfinite(fmin) and math.isfinite(fmax)):
        raise TTLError(f"{option}: frequencies must be finite, got {fmin:g} {fmax:g}")
    if fmin <= 0:
        raise TTLError(f"{option}: FMIN must be positive, got {fmin:g} Hz")
    if fmax <= fmin:
        raise TTLError(f"{option}: FMAX must be above FMIN, got {fmin:g} {fmax:g} Hz")
    nyquist = min(fs, FIT_FS) / 2
    if fmax > nyquist:
        raise TTLError(f"{option}: FMAX {fmax:g} Hz is above the Nyquist frequency {nyquist:g} Hz of the fit")
    if segment_duration is not None:
        nbins = math.floor(fmax * segment_duration) - math.ceil(fmin * segment_duration) + 1
        if nbins < 5:
            raise TTLError(
                f"{option}: {fmin:g}-{fmax:g} Hz holds only {max(nbins, 0)} frequency bins of "
                f"{segment_duration:g} s segments; widen the band or lengthen --segment"
            )
    return fmin, fmax


def data_loss(tm, td) -> dict:
    """The data lost to gaps: NaN stretches of the telemetry (eta or DWS, sample ranges
    ``[start, stop)``) and the fraction of TDI samples they spoil (the interpolation and the
    nested delays spread each gap by about 70 s; ``ttlcore.estimate.fit.spectra_of_segment`` masks
    those samples and drops an FFT segment less than half valid)."""
    bad = tm.missing()
    stretches = tm.nan_stretches()
    tdi_bad = ~(np.isfinite(td.data).all(axis=0) & np.isfinite(td.regressors).all(axis=(0, 1)))
    return {
        "telemetry_samples_missing": int(bad.sum()),
        "stretches": stretches,
        "seconds_missing": float(bad.sum() / tm.fs),
        "tdi_fraction_lost": float(tdi_bad.mean()),
    }


def _check_segment(segment: float, duration: float, path) -> None:
    if segment > duration:
        raise TTLError(
            f"--segment: {segment:g} s segments need at least that much data, but {path} "
            f"holds {duration:g} s; give a shorter --segment"
        )


def check_method(method: str) -> str:
    m = str(method).strip().lower()
    if m not in METHODS:
        raise TTLError(f"--method: unknown method {method!r}; use one of {', '.join(METHODS)}")
    return m


# ---------------------------------------------------------------------------
# Truth
# ---------------------------------------------------------------------------


class _Truth:
    """What the analysis knows of the truth: a coefficient source and maybe a TTL series."""

    def __init__(self, path: Path, source: str, coefficients=None, series=None, ttl=None, t=None):
        self.path = path
        self.source = source  # "ttl-truth" or "lisainstrument"
        self.static = coefficients  # (24,) for lisainstrument
        self.series = series  # (24, n) on the data's samples, our truth files
        self.ttl = ttl  # (6, n) on the data's samples, our truth files
        self.t = t  # (n,) sample times

    def mean_coefficients(self, t_start: float, t_stop: float) -> tuple[np.ndarray, bool]:
        """Mean true coefficients over ``[t_start, t_stop)`` and whether they vary in time."""
        if self.series is None:
            return np.asarray(self.static, dtype=float), False
        sel = (self.t >= t_start) & (self.t < t_stop)
        if not sel.any():
            sel = slice(None)
        s = self.series[:, sel]
        varying = bool(np.any(np.ptp(s, axis=1) > 1e-12 * np.maximum(np.abs(s).max(axis=1), 1e-30)))
        return s.mean(axis=1), varying


#: Configuration entries a telemetry file and its truth file must share.
_SIMULATION_KEYS = ("seed", "orbit", "coefficients", "noises", "t0", "fs")


def load_truth(path, tm, data_kind: str, data_path) -> _Truth:
    """Truth for telemetry ``tm`` from ``path`` (our truth file or a lisainstrument file)."""

    path = Path(path)
    kind = file_kind(path)
    if kind == "ttl":
        raise TelemetryError(
            path,
            f"--truth names a telemetry file, not a truth file (ours sit beside the data as {default_truth_path(path).name})",
        )
    if kind == "lisainstrument":
        if data_kind != "lisainstrument":
            raise TelemetryError(
                path,
                "--truth: a lisainstrument file gives the truth of lisainstrument data only; "
                f"for {Path(data_path).name} give its truth file {default_truth_path(data_path).name}",
            )
        flat = lisainstrument_truth(path)
        return _Truth(path, "lisainstrument", coefficients=np.array([flat[n] for n in COEFFICIENT_NAMES]))
    # our truth file: align it with the data's samples
    tr = read_truth(path)
    if abs(tr.fs - tm.fs) > 1e-9 * tm.fs:
        raise TelemetryError(path, f"sampled at {tr.fs:g} Hz but the data at {tm.fs:g} Hz", "@fs")
    i0 = int(round((tm.t0 - tr.t0) * tm.fs))
    if abs(i0 / tm.fs - (tm.t0 - tr.t0)) > 1e-3 / tm.fs or i0 < 0 or i0 + tm.size > tr.size:
        raise TelemetryError(
            path,
            f"does not cover the data's samples (data t0 {tm.t0:g} s, {tm.size} samples; "
            f"truth t0 {tr.t0:g} s, {tr.size} samples); wrong truth file?",
            "@t0",
        )
    if tm.config and tr.config:
        differ = [k for k in _SIMULATION_KEYS if tm.config.get(k) != tr.config.get(k)]
        if differ:
            raise TelemetryError(
                path,
                f"belongs to another simulation than {Path(data_path).name} "
                f"(configuration differs in {', '.join(differ)}); wrong truth file?",
                "@config",
            )
    sl = slice(i0, i0 + tm.size)
    return _Truth(path, "ttl-truth", series=tr.coefficients[:, sl], ttl=tr.ttl[:, sl], t=tm.t)


# ---------------------------------------------------------------------------
# The analysis
# ---------------------------------------------------------------------------


def analyze(
    data_path,
    *,
    truth_path=None,
    band=DEFAULT_BAND,
    method: str = "gls",
    out_dir,
    settings: FitSettings | None = None,
    progress=None,
    figures: bool = True,
    mcmc_options: dict | None = None,
) -> dict:
    """Fit the TTL coefficients of a telemetry file, subtract them and write the results.

    Parameters
    ----------
    data_path : path-like
        Our telemetry file or a lisainstrument 2.x measurement file.
    truth_path : path-like, optional
        Our truth file, or for lisainstrument data the lisainstrument file (see the module
        docstring).  Only used for comparisons, never by the fit.
    band : (float, float)
        Fit band [Hz] (overrides ``settings.band``).
    method : ``"gls"`` or ``"mcmc"``
        ``"mcmc"`` samples the same likelihood with :func:`ttlcore.estimate.mcmc.fit_mcmc`, on the
        segment spectra of a GLS run (whose coefficients are kept in ``fit.json`` under
        ``gls_coefficients`` for comparison).
    out_dir : path-like
        Directory for ``fit.json``, ``asd_X.png`` and ``coefficients.png`` (created).
    settings : FitSettings, optional
        Fit settings (segment length, window, ...); default :class:`FitSettings`.
    progress : callable(str), optional
        Called with a short message at the start of each long step.
    figures : bool
        Draw the figures (default True).
    mcmc_options : dict, optional
        Extra keyword arguments of ``fit_mcmc`` (``noise_levels``, ``seed``).

    Returns
    -------
    dict
        ``fit`` (:class:`~ttlcore.estimate.fit.FitResult`), ``fit_json`` (what was written),
        ``subtraction`` (:class:`~ttlcore.estimate.subtraction.SubtractionResult`, X2/Y2/Z2),
        ``tdi`` (the :class:`~ttlcore.tdi.data.TDIData`), ``paths`` (output files) and
        ``timings`` [s].

    Raises
    ------
    TTLError, TelemetryError
        One-line messages naming the file or option at fault.
    """

    say = progress or (lambda msg: None)
    clock = _Laps()
    method = check_method(method)
    s = replace(settings or FitSettings(), band=tuple(float(b) for b in band))
    data_path = Path(data_path)
    out_dir = Path(out_dir)
    # --- check the inputs before any work (and before any progress output)
    data_kind = _check_inputs(data_path, truth_path, out_dir, s)

    # --- read
    say(f"reading {data_path}")
    tm = read_telemetry(data_path)
    check_band(s.band, fs=tm.fs, segment_duration=s.segment_duration)
    _check_segment(s.segment_duration, tm.duration, data_path)
    if settings is None or settings.dws_asd is None:
        # errors-in-variables term at the DWS noise level the data were made with (0 if off)
        s = replace(s, dws_asd=dws_asd_from_config(tm.config))
    truth = load_truth(truth_path, tm, data_kind, data_path) if truth_path is not None else None
    clock.lap("read")

    # --- TDI
    say(f"TDI of data and 24 regressors ({tm.size} samples at {tm.fs:g} Hz)")
    td = compute_tdi(tm)
    loss = data_loss(tm, td)
    if loss["telemetry_samples_missing"]:
        say(
            f"gaps: {loss['telemetry_samples_missing']} telemetry samples missing (NaN) in "
            f"{len(loss['stretches'])} stretch(es); {100 * loss['tdi_fraction_lost']:.2f} % of the TDI samples lost "
            "(the fit masks them)"
        )
    clock.lap("tdi")

    # --- fit (truth never enters here)
    say(f"fit ({method}, {s.band[0]:g}-{s.band[1]:g} Hz, {s.segment_duration:g} s segments)")
    res = _fit(td, s, method, say, mcmc_options, data_path)
    clock.lap("fit")

    # --- truth over the fit window
    truth_mean, notes = _truth_over_fit(truth, res)

    # --- subtraction
    say("subtraction in the time domain")
    sub = analyse_subtraction(
        td, res.coefficients, true_coefficients=truth_mean, ttl_truth=None if truth is None else truth.ttl, ltt=tm.ltt
    )
    clock.lap("subtraction")

    # --- fit.json
    paths = {"fit_json": out_dir / "fit.json"}
    if figures:
        paths["asd_x"] = out_dir / "asd_X.png"
        paths["coefficients"] = out_dir / "coefficients.png"
    content = res.to_json(truth=truth_mean)
    content["units"] = "m/rad"
    content["data"] = {
        "file": str(data_path),
        "kind": data_kind,
        "t0": tm.t0,
        "fs": tm.fs,
        "size": tm.size,
        "duration_s": tm.duration,
    }
    content["data_loss"] = loss
    content["truth_file"] = None if truth is None else str(truth.path)
    content["truth_source"] = None if truth is None else truth.source
    content["ttl_residual_available"] = sub.ttl_residual is not None
    content["settings"] = _settings_json(s)
    content["notes"] = notes
    content["files"] = {k: str(v) for k, v in paths.items()}
    # made only now that the fit has succeeded: a failed analysis (all data NaN, a singular
    # fit) leaves no empty directory behind
    out_dir.mkdir(parents=True, exist_ok=True)

    # --- figures
    if figures:
        say("ASDs and figures")
        _figures(td, sub, res, s, truth_mean, paths, content, f"{data_path.name}: {method.upper()} fit")
        clock.lap("figures")
    content["timings_s"] = clock.timings
    write_json(paths["fit_json"], content)
    return {
        "fit": res,
        "fit_json": content,
        "subtraction": sub,
        "tdi": td,
        "paths": paths,
        "timings": clock.timings,
        "notes": notes,
    }


class _Laps:
    """The wall time [s] of each step of the analysis (``timings``: step -> seconds, rounded
    to ms), a step ending at each :meth:`lap`."""

    def __init__(self):
        self.timings: dict[str, float] = {}
        self.clock = time.monotonic()

    def lap(self, name: str) -> None:
        now = time.monotonic()
        self.timings[name] = round(now - self.clock, 3)
        self.clock = now


def _check_inputs(data_path: Path, truth_path, out_dir: Path, s: FitSettings) -> str:
    """The checks of :func:`analyze` before any work: the segment length and band, the output
    directory, the files' kinds (and for our files, the segment against the duration).
    Returns the data file's kind; raises TTLError or TelemetryError naming the option or file."""
    if not (math.isfinite(s.segment_duration) and s.segment_duration > 0):
        raise TTLError(f"--segment: must be a positive duration, got {s.segment_duration!r}")
    check_band(s.band, segment_duration=s.segment_duration)
    if out_dir.exists() and not out_dir.is_dir():
        raise TTLError(f"--out: {out_dir} exists and is not a directory")
    data_kind = file_kind(data_path)
    if data_kind == "truth":
        raise TelemetryError(
            data_path, "this is a truth file; analyse the telemetry file beside it (pass this one with --truth)"
        )
    if truth_path is not None:
        file_kind(truth_path)
    if data_kind == "ttl":  # our files tell their length without reading the series
        _check_segment(s.segment_duration, read_header(data_path)["duration"], data_path)
    return data_kind


def _fit(td, s: FitSettings, method: str, say, mcmc_options: dict | None, data_path: Path):
    """The fit of :func:`analyze` (GLS or MCMC), its failures as TTLError naming the file."""
    try:
        if method == "gls":
            res, _ = fit_tdi(td, s, "gls")
        else:
            res = _fit_mcmc(td, s, say, mcmc_options)
    except np.linalg.LinAlgError:
        raise TTLError(
            f"{data_path}: the fit's normal equations are singular (no jitter in the DWS readouts, "
            "or too little data in the band?)"
        ) from None
    except ValueError as exc:
        raise TTLError(f"{data_path}: fit failed: {exc}") from None
    return res


def _truth_over_fit(truth: _Truth | None, res) -> tuple:
    """The true coefficients averaged over the fit window of ``res`` (None without truth)
    and the notes on what the truth allows."""
    notes: list[str] = []
    truth_mean = None
    if truth is not None:
        truth_mean, varying = truth.mean_coefficients(res.t_start, res.t_stop)
        if varying:
            notes.append(
                "true coefficients vary in time: 'truth' is their mean over the fit window, "
                "and the residual with true coefficients uses that mean"
            )
        if truth.ttl is None:
            notes.append(
                "the truth (lisainstrument file) holds no TTL time series: TTL residual and "
                "noise without TTL are not computed"
            )
    else:
        notes.append("no truth given: coefficient errors, TTL residual and noise without TTL not computed")
    return truth_mean, notes


def _settings_json(s: FitSettings) -> dict:
    """The fit settings ``fit.json`` records."""
    return {
        "segment_duration": s.segment_duration,
        "window": s.window,
        "overlap": s.overlap,
        "notch": s.notch,
        "eiv": s.eiv,
        "robust_covariance": s.robust_covariance,
        "fit_fs": FIT_FS,
    }


def _figures(td, sub, res, s: FitSettings, truth_mean, paths: dict, content: dict, title: str) -> None:
    """The X ASDs (and their ratios to the requirement, into ``content``) and the
    coefficients drawn to ``paths``; ``title`` is completed with the band."""
    arm = C * float(np.mean(td.ltt_mean))
    curves = asd_x_curves(sub, arm_length=arm)
    content["asd_x_vs_requirement"] = requirement_summary(curves, s.band)
    title = f"{title} {s.band[0]:g}-{s.band[1]:g} Hz"
    plot_asd_x(sub, paths["asd_x"], band=s.band, arm_length=arm, title=title, curves=curves)
    plot_coefficients(
        res.names,
        res.coefficients,
        res.sigma,
        paths["coefficients"],
        truth=truth_mean,
        title=f"{title}, chi2/dof {res.chi2_dof:.3f}",
    )


def _fit_mcmc(td, s: FitSettings, say, options: dict | None):
    """MCMC over the same likelihood (:func:`ttlcore.estimate.mcmc.fit_mcmc`, which runs its own GLS
    first for the noise weights and keeps its coefficients in ``extra``)."""
    spectra = segment_spectra(td, s.band, s.segment_duration, s.window, s.overlap, s.decimate)
    last = [0.0]

    def report(n_steps, max_tau, target):
        now = time.monotonic()
        if now - last[0] > 10:
            last[0] = now
            say(f"MCMC: {n_steps} steps, autocorrelation time {max_tau:.0f} (target {target:.0f})")

    opts = dict(options or {})
    opts.setdefault("progress", report)
    res, _ = fit_mcmc(spectra, td.ltt_mean, s, td.names, **opts)
    return res


def requirement_summary(curves: dict, band) -> dict:
    """Ratios of the log-averaged X ASDs to the (equally averaged) requirement inside ``band``:
    ``{series: {"median": ..., "max": ..., "f_max": ...}}``."""
    f, req = curves["requirement"]
    sel = (f >= band[0]) & (f <= band[1]) & (req > 0)
    out = {}
    for name, (_fc, asd) in curves.items():
        if name == "requirement" or not sel.any():
            continue
        ratio = asd[sel] / req[sel]
        k = int(np.argmax(ratio))
        out[name] = {"median": float(np.median(ratio)), "max": float(ratio[k]), "f_max": float(f[sel][k])}
    return out
