r"""The paper's scenarios in one command (``ttl scenarios --out DIR``), and beyond.

Cases (:data:`PAPER_CASES`; the paper's section in brackets)
-------------------------------------------------------------
==================  ======================================================================
``static_unequal``  static unequal arms, no GW (sec. IV)
``keplerian``       Keplerian arms, no GW (sec. IV)
``vb``              HM Cnc + ZTF J1539, Keplerian arms, t0 = 0 (sec. V A)
``sgwb``            stochastic background h^2 Omega = 1.15e-12 (f / 3 mHz)^(2/3), Keplerian (V B)
``gb1``, ``gb2``    galactic white-dwarf population, Keplerian arms, the paper's two
                    epochs t0 = 10 s and 10 303 235 s (table I) (V C)
``mbhb1/2``         each merger, static equal arms, the paper's t0 and t_c (table II) (V D)
``all``             VB + galaxy + background + MBHB2, MBHB2's day (V E)
``mbhb2_200mhz``    MBHB2 with the fit band ending at 0.2 Hz (appendix B)
==================  ======================================================================

The paper used ESA orbits for the VB and SGWB days and equal-arm *moving* orbits for the
Sangria days; we use Keplerian orbits where the constellation's motion matters (the galaxy's
two epochs) and static equal arms for the mergers (a day-long merger does not need the
motion). With a ``duration`` shorter than a day, the merger times move with it
(``t_c = t0 + (t_c - t0)_paper * duration / 1 day``: still mid-run).

Every case is also run without GW as the reference, with the *same* noise realisation (same
seed): the simulation without GW is done once per (orbit, t0) and the GW link responses,
made by the simulator's injection hook (:mod:`ttlcore.gw.injection`) on the same times and
orbit, are added to ``eta`` - TDI and the fit's regressors are linear, so the data with GW
is exactly what ``ttl simulate --gw`` writes. From the truth: "TTL plus GW only" is
``TDI(ttl) + TDI(gw)``; "everything but TTL" is ``TDI(eta) - TDI(ttl)``.

Per case (``summary.json``; ``summary.md`` is the same as tables)
-----------------------------------------------------------------
- ``max_abs_error_mm``, ``rms_error_mm``: ``|C_fit - C_true|`` over the 24 [mm/rad];
- ``chi2_dof`` of the fit;
- ``fraction_above_requirement``: fraction of the log-spaced frequency bins in the fit band
  where the ASD of the X2 residual exceeds the requirement, counting only bins that are *not*
  GW-dominated (GW ASD below the ASD of the reference's residual);
- ``gw_intact``: on the Welch bins (f >= 0.1 mHz) where the GW's X2 ASD exceeds the TTL
  residual's (``TDI(true TTL) - fitted model``) by a factor 10, the largest relative
  deviation of the ASD of "TTL plus GW only minus fitted model" from the GW's ASD; pass if
  below 5 % (``n_bins`` tells how many bins it covers);
- ``shift_over_sigma_max``: ``max_k |C_k(with GW) - C_k(without)| / sigma_k``, and the GW's
  in-band signal-to-noise ratio in X2 against the reference residual,
  ``snr_band = sqrt(2 T sum_f P_gw(f) / P_res(f) df)`` (a deterministic signal's
  ``4 int |h~|^2 / S_n``), which tells whether a shift above 2 sigma is explained by a loud
  signal (the whitening is re-estimated from the residual, which a loud signal changes).

Variants (beyond the paper): ``paper`` (2.3 mm/rad, white jitter above 0.8 mHz),
``lisainstrument`` (lisainstrument's default coefficient set) and ``coloured`` (jitter ASDs
with their knee at 8 mHz instead of 0.8 mHz and a high-frequency corner at 0.1 Hz, so the
jitter - and the TTL noise - falls as ``f^-2`` over the lower and the upper part of the
fit band and is white only between; the paper's open question).

Figures per case and variant: ``<variant>/<case>_asd.png`` (X2 ASDs: data, residual, TTL
residual, noise without TTL, GW, requirement), ``<case>_coefficients.png`` (deviations with
and without GW), ``<case>_gw_intact.png`` (the paper's close-up: GW ASD, residual of "TTL
plus GW only" after subtraction, noise without TTL, residual of the data).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..conventions import (
    COEFFICIENT_NAMES,
    DAY,
    C,
)
from ..errors import TTLError
from ..estimate.fit import DEFAULT_BAND, FitSettings, fit_tdi
from ..estimate.noise_psd import requirement_x2
from ..estimate.spectra import log_average, welch_asd
from ..estimate.subtraction import ttl_in_tdi
from ..gw.injection import parse_gw_spec
from ..io.atomic import write_json, write_text
from ..plots.scenarios import scenario_figures
from ..sim.coefficients import make_coefficients
from ..sim.simulator import NoiseSwitches, SimulationConfig, simulate
from ..tdi.combinations import MICHELSON, build
from ..tdi.data import compute_tdi

__all__ = ["Case", "PAPER_CASES", "VARIANTS", "run_scenarios"]


@dataclass(frozen=True)
class Case:
    """One scenario: orbit, start time, GW sources (``--gw`` names) and fit band."""

    name: str
    title: str
    orbit: str
    t0: float
    gw: str = ""
    band: tuple = tuple(DEFAULT_BAND)
    #: merger time after t0 in a one-day run [s] (scaled with the duration)
    tc_offset: float | None = None
    merger: bool = False


PAPER_CASES = (
    Case("static_unequal", "static unequal arms", "unequal", 0.0),
    Case("keplerian", "Keplerian arms", "keplerian", 0.0),
    Case("vb", "verification binaries (HM Cnc, ZTF J1539)", "keplerian", 0.0, "hmcnc,ztfj1539"),
    Case("sgwb", "stochastic background", "keplerian", 0.0, "sgwb"),
    Case("gb1", "galactic binaries, epoch 1 (t0 = 10 s)", "keplerian", 10.0, "galaxy"),
    Case("gb2", "galactic binaries, epoch 2 (t0 = 10303235 s)", "keplerian", 10303235.0, "galaxy"),
    Case("mbhb1", "MBHB1 merger", "equal", 13.57e6, "mbhb1", tc_offset=0.05e6, merger=True),
    Case("mbhb2", "MBHB2 merger", "equal", 11.22e6, "mbhb2", tc_offset=0.04e6, merger=True),
    Case(
        "all",
        "all sources (VB, galaxy, background, MBHB2)",
        "equal",
        11.22e6,
        "hmcnc,ztfj1539,galaxy,sgwb,mbhb2",
        tc_offset=0.04e6,
        merger=True,
    ),
    Case(
        "mbhb2_200mhz",
        "MBHB2, fit band 3 mHz - 0.2 Hz",
        "equal",
        11.22e6,
        "mbhb2",
        band=(3e-3, 0.2),
        tc_offset=0.04e6,
        merger=True,
    ),
)

#: Variants: coefficient set, jitter knee and high-frequency corner [Hz] (None: white above the knee).
VARIANTS = {
    "paper": {
        "coeffs": "paper",
        "fknee": 0.8e-3,
        "fhigh": None,
        "title": "paper: 2.3 mm/rad, white jitter in the band",
    },
    "lisainstrument": {
        "coeffs": "lisainstrument",
        "fknee": 0.8e-3,
        "fhigh": None,
        "title": "lisainstrument default coefficients, white jitter",
    },
    "coloured": {
        "coeffs": "paper",
        "fknee": 8e-3,
        "fhigh": 0.1,
        "title": "2.3 mm/rad, coloured jitter (f^-2 below 8 mHz and above 0.1 Hz)",
    },
}

#: Acceptance thresholds of the issue / paper [m/rad] and the GW-intact tolerance.
MAX_ERROR = 0.1e-3
MAX_ERROR_NO_MERGER = 0.06e-3
GW_INTACT_TOLERANCE = 0.05
GW_INTACT_FACTOR = 10.0


def _welch(x: np.ndarray, fs: float, nperseg: int):
    """Welch PSD (:func:`ttlcore.estimate.spectra.welch_asd` squared)."""
    f, asd = welch_asd(x, fs, nperseg)
    return f, asd**2


class _Runner:
    """Caches shared between cases: base simulations, TDI, reference fits, GW signals."""

    def __init__(self, duration: float, seed: int, say, fit_settings: FitSettings | None = None):
        self.duration = float(duration)
        self.seed = int(seed)
        self.say = say
        self.fit_settings = fit_settings or FitSettings()
        self._gw_cache: dict = {}

    # -- simulation ---------------------------------------------------------------------
    def base(self, orbit: str, t0: float, variant: dict) -> dict:

        cfg = SimulationConfig(
            duration=self.duration,
            t0=t0,
            orbit=orbit,
            seed=self.seed,
            coefficients=make_coefficients(variant["coeffs"], seed=self.seed),
        )
        cfg.jitter = dict(cfg.jitter, fknee=variant["fknee"])
        if variant.get("fhigh"):
            cfg.jitter["fhigh"] = variant["fhigh"]
        self.say(
            f"simulate {orbit} t0={t0:g} s ({self.duration:g} s, {variant['coeffs']} coefficients, "
            f"jitter knee {1e3 * variant['fknee']:g} mHz)"
        )
        tm, truth = simulate(cfg)
        self.say("TDI of data and regressors")
        td = compute_tdi(tm)
        ttl_xyz = ttl_in_tdi(truth["ttl"], tm.ltt, tm.fs, tm.t0)
        return {"config": cfg, "tm": tm, "td": td, "ttl_xyz": ttl_xyz, "fits": {}}

    def gw(self, case: Case, base: dict) -> tuple[np.ndarray, dict, list, float | None]:
        """GW link responses (6, n) of a case (sum) and per source, by the simulator's injection hook."""

        t_c = None
        if case.tc_offset is not None:
            t_c = case.t0 + case.tc_offset * self.duration / DAY
        key = (case.gw, case.orbit, case.t0, self.duration, t_c)
        if key not in self._gw_cache:
            inj = parse_gw_spec(case.gw, t0=case.t0, duration=self.duration, seed=self.seed, t_c=t_c)
            self.say(f"GW signals: {', '.join(i.name for i in inj)}")
            cfg = SimulationConfig(
                duration=self.duration,
                t0=case.t0,
                orbit=case.orbit,
                seed=self.seed,
                noises=NoiseSwitches.parse("none"),
                injections=inj,
            )
            tm, truth = simulate(cfg)
            parts = {k.split("/", 1)[1]: v for k, v in truth.items() if k.startswith("injections/")}
            # kept for the other variants (a day of six links is 17 MB per source)
            self._gw_cache[key] = (tm.eta, parts, [i.describe() for i in inj], t_c)
        return self._gw_cache[key]

    def fit(self, td, band, variant: dict):
        s = replace(self.fit_settings, band=tuple(band), dws_asd=70e-9 / 335)
        res, _ = fit_tdi(td, s)
        return res


def _tdi_of_links(y: np.ndarray, tm) -> np.ndarray:

    built = build(MICHELSON, tm.ltt, tm.fs)
    return np.stack([b(y) for b in built])


def _snr_band(f, p_gw, p_noise, band, duration) -> float:
    sel = (f >= band[0]) & (f <= band[1]) & (p_noise > 0)
    if not np.any(sel):
        return 0.0
    df = f[1] - f[0]
    return float(math.sqrt(2 * duration * np.sum(p_gw[sel] / p_noise[sel]) * df))


def analyse_case(
    case: Case, base: dict, runner: _Runner, variant: dict, out_dir: Path | None, figures: bool = True
) -> dict:
    """Fit with and without GW, subtraction, the summary metrics and (optionally) figures of one case."""

    td, tm, cfg = base["td"], base["tm"], base["config"]
    band = tuple(case.band)
    bkey = band
    if bkey not in base["fits"]:
        runner.say(f"fit without GW ({band[0]:g}-{band[1]:g} Hz)")
        base["fits"][bkey] = runner.fit(td, band, variant)
    ref = base["fits"][bkey]
    n = td.size
    if case.gw:
        gw_links, parts, described, t_c = runner.gw(case, base)
        gw_xyz = _tdi_of_links(gw_links, tm)
        td_gw = replace(td, data=td.data + gw_xyz)
        runner.say(f"fit with GW ({case.name})")
        res = runner.fit(td_gw, band, variant)
    else:
        gw_xyz, parts, described, t_c = np.zeros((3, n)), {}, [], None
        td_gw, res = td, ref
    truth = (
        cfg.coefficients.mean(res.t_start, res.t_stop)
        if np.isfinite(res.t_start)
        else cfg.coefficients.mean(tm.t0, tm.t0 + tm.duration)
    )
    err = res.coefficients - truth
    shift = res.coefficients - ref.coefficients
    z = shift / ref.sigma

    # series in X2 (index 0)
    model = td.model(res.coefficients)
    ttl_xyz = base["ttl_xyz"]
    series = {
        "data": td_gw.data,
        "residual": td_gw.data - model,
        "ttl_residual": ttl_xyz - model,
        "noise_without_ttl": td_gw.data - ttl_xyz,
        "ttl_plus_gw_residual": ttl_xyz + gw_xyz - model,
        "gw": gw_xyz,
        "reference_residual": td.data - td.model(ref.coefficients),
    }
    x = {k: v[0] for k, v in series.items()}
    ok = np.all([np.isfinite(v) for v in x.values()], axis=0)
    fs = tm.fs
    nper = int(min(2**14, 2 ** np.floor(np.log2(max(ok.sum() / 4, 64)))))
    welch = {k: _welch(v[ok], fs, nper) for k, v in x.items()}
    f = welch["data"][0]
    P = {k: v[1] for k, v in welch.items()}

    intact = _gw_intact(f if case.gw else None, P)
    fc, req, considered, gw_dom, frac = _above_requirement(f, P, band, td)
    inband = (fc >= band[0]) & (fc <= band[1])

    snr = _snr_band(f, P["gw"], P["reference_residual"], band, ok.sum() / fs) if case.gw else 0.0
    mm = 1e3
    out = {
        "case": case.name,
        "title": case.title,
        "orbit": case.orbit,
        "t0": case.t0,
        "duration_s": tm.duration,
        "gw": case.gw or None,
        "gw_sources": described,
        "t_c": t_c,
        "band_hz": list(band),
        "merger": case.merger,
        "max_abs_error_mm": float(mm * np.max(np.abs(err))),
        "worst_coefficient": COEFFICIENT_NAMES[int(np.argmax(np.abs(err)))],
        "rms_error_mm": float(mm * np.sqrt(np.mean(err**2))),
        "reference_max_abs_error_mm": float(mm * np.max(np.abs(ref.coefficients - truth))),
        "chi2_dof": float(res.chi2_dof),
        "median_sigma_mm": float(mm * np.median(res.sigma)),
        "fraction_above_requirement": frac,
        "n_bins_considered": int(considered.sum()),
        "n_bins_gw_dominated": int((inband & gw_dom).sum()),
        "gw_intact": intact,
        "shift_over_sigma_max": float(np.max(np.abs(z))),
        "shift_worst_coefficient": COEFFICIENT_NAMES[int(np.argmax(np.abs(z)))],
        "shift_max_mm": float(mm * np.max(np.abs(shift))),
        "snr_band_x2": snr,
        "gw_rms_links": float(np.sqrt(np.mean(gw_links**2))) if case.gw else 0.0,
        "gw_rms_links_per_source": {k: float(np.sqrt(np.mean(v**2))) for k, v in parts.items()},
        "coefficients_error_mm": dict(zip(COEFFICIENT_NAMES, (mm * err).round(6).tolist())),
        "sigma_mm": dict(zip(COEFFICIENT_NAMES, (mm * res.sigma).round(6).tolist())),
        "shift_over_sigma": dict(zip(COEFFICIENT_NAMES, z.round(4).tolist())),
        "limit_mm": (MAX_ERROR if case.merger else MAX_ERROR_NO_MERGER) * mm,
    }
    out["error_within_limit"] = out["max_abs_error_mm"] < out["limit_mm"]
    out["shift_within_2sigma"] = out["shift_over_sigma_max"] < 2.0
    if figures and out_dir is not None:
        arm = C * float(np.mean(td.ltt_mean))
        out["figures"] = scenario_figures(
            case, out, f, P, fc, req, band, arm, res, ref, truth, out_dir, intact_factor=GW_INTACT_FACTOR
        )
    return out


def _gw_intact(f: np.ndarray | None, P: dict) -> dict:
    """Whether the GW is intact after the subtraction, per Welch bin (frequencies ``f``
    [Hz], None without GW; ``P``: the X2 PSDs by series): in the bins where the GW exceeds
    ``GW_INTACT_FACTOR`` times the TTL residual, the largest relative deviation of the ASD
    of (TTL + GW - fitted model) from the GW's."""
    intact: dict = {
        "n_bins": 0,
        "max_relative_deviation": None,
        "pass": None,
        "factor": GW_INTACT_FACTOR,
        "tolerance": GW_INTACT_TOLERANCE,
    }
    if f is not None:
        sel = (f >= 1e-4) & (P["gw"] > GW_INTACT_FACTOR**2 * P["ttl_residual"]) & (P["gw"] > 0)
        intact["n_bins"] = int(sel.sum())
        if sel.any():
            dev = np.abs(np.sqrt(P["ttl_plus_gw_residual"][sel] / P["gw"][sel]) - 1)
            intact["max_relative_deviation"] = float(dev.max())
            intact["f_range_hz"] = [float(f[sel].min()), float(f[sel].max())]
            intact["pass"] = bool(dev.max() < GW_INTACT_TOLERANCE)
    return intact


def _above_requirement(f: np.ndarray, P: dict, band, td) -> tuple:
    """The requirement outside GW-dominated bins (log-averaged bins in the fit ``band``
    [Hz]): the bins' frequencies, the requirement there, the bins considered, the
    GW-dominated ones and the fraction of those considered where the residual exceeds it."""
    fc, lp = log_average(f[1:], np.stack([P["residual"][1:], P["gw"][1:], P["reference_residual"][1:]]))
    _, req = log_average(f[1:], requirement_x2(f[1:], C * float(np.mean(td.ltt_mean))))
    inband = (fc >= band[0]) & (fc <= band[1])
    gw_dom = lp[1] > lp[2]
    considered = inband & ~gw_dom
    above = considered & (lp[0] > req)
    frac = float(above.sum() / considered.sum()) if considered.any() else float("nan")
    return fc, req, considered, gw_dom, frac


def _md_table(rows: list[dict]) -> str:
    head = (
        "| case | GW | max err [mm/rad] | RMS err | limit | chi2/dof | frac > req | GW intact (bins, max dev) "
        "| shift/sigma max | SNR band |\n|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        gi = r["gw_intact"]
        if r["gw"]:
            dev = gi["max_relative_deviation"]
            intact = (
                f"{gi['n_bins']}, {100 * dev:.2f} % {'ok' if gi['pass'] else 'FAIL'}"
                if dev is not None
                else f"{gi['n_bins']} bins (GW never 10x TTL residual)"
            )
        else:
            intact = "-"
        lines.append(
            f"| {r['case']} | {r['gw'] or '-'} | {r['max_abs_error_mm']:.4f} {'ok' if r['error_within_limit'] else 'FAIL'} "
            f"| {r['rms_error_mm']:.4f} | {r['limit_mm']:.2f} | {r['chi2_dof']:.3f} | {r['fraction_above_requirement']:.3f} "
            f"| {intact} | {r['shift_over_sigma_max']:.2f} ({r['shift_worst_coefficient']}) | {r['snr_band_x2']:.1f} |"
        )
    return head + "\n".join(lines) + "\n"


def _run_group(runner: _Runner, vname: str, names, vdir: Path, figures: bool) -> list[dict]:
    """The rows of the cases ``names`` (sharing one orbit and t0) of variant ``vname``."""
    by_name = {c.name: c for c in PAPER_CASES}
    group = [by_name[n] for n in names]
    variant = VARIANTS[vname]
    base = runner.base(group[0].orbit, group[0].t0, variant)
    rows = []
    for c in group:
        runner.say(f"[{vname}] case {c.name}")
        rows.append(analyse_case(c, base, runner, variant, vdir, figures=figures))
    return rows


def _check_scenarios(cases: list, variants: list, by_name: dict, duration: float, fit_settings):
    """The arguments of :func:`run_scenarios` checked (TTLError naming the option); returns
    the fit settings, their segment shortened to ``duration`` [s] when longer."""
    unknown = [c for c in cases if c not in by_name]
    if unknown:
        raise TTLError(f"--cases: unknown {', '.join(unknown)}; known: {', '.join(by_name)}")
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        raise TTLError(f"--variants: unknown {', '.join(bad)}; known: {', '.join(VARIANTS)}")
    if not (math.isfinite(duration) and duration > 0):
        raise TTLError(f"--duration: must be positive, got {duration}")
    seg = (fit_settings or FitSettings()).segment_duration
    if duration < seg:
        fit_settings = replace(fit_settings or FitSettings(), segment_duration=float(duration))
    return fit_settings


def _submit(client, variants: list, groups: dict, out_dir: Path, args: tuple) -> dict:
    """One Dask task per (variant, base simulation) of :func:`run_scenarios` (``args``:
    duration [s], seed, fit settings, figures); returns their futures by that pair."""
    duration, seed, fit_settings, figures = args
    futures = {}
    for vname in variants:
        (out_dir / vname).mkdir(exist_ok=True)
        for key, names in groups.items():
            futures[vname, key] = client.submit(
                _group_task,
                duration,
                seed,
                fit_settings,
                vname,
                names,
                str(out_dir / vname),
                figures,
                pure=False,
                retries=1,
            )
    return futures


def _summary_md(summary: dict, duration: float, seed: int) -> list[str]:
    """The parts of ``summary.md``: the legend and one table per variant."""
    md = [
        "# TTL subtraction with GW signals: scenario summary\n",
        f"{duration:g} s per case, seed {seed}, total {summary['timings_s']['total']:.0f} s. "
        "Errors in mm/rad; limit 0.06 mm/rad without merger, 0.1 with (the paper's). "
        "'frac > req': fraction of log-spaced bins in the fit band, outside GW-dominated ones, where the X2 "
        "residual exceeds the requirement. 'GW intact': bins where the GW ASD exceeds 10x the TTL residual, "
        "and the largest relative deviation there of the ASD of (TTL + GW only - fitted model) from the GW's "
        "(pass < 5 %). 'shift/sigma': largest (C with GW - C without) / sigma; 'SNR band': GW in-band SNR in X2.\n",
    ]
    for vname, v in summary["variants"].items():
        md.append(f"\n## {vname}: {v['title']}\n\n")
        md.append(_md_table(v["cases"]))
    return md


def _group_task(duration, seed, fit_settings, vname, names, vdir, figures) -> list[dict]:
    """:func:`_run_group` as a Dask task (its own runner; the caches only hold
    deterministic results, so the rows equal those of the serial run)."""
    return _run_group(_Runner(duration, seed, lambda msg: None, fit_settings), vname, names, Path(vdir), figures)


def run_scenarios(
    out_dir,
    *,
    cases=None,
    variants=("paper", "lisainstrument", "coloured"),
    duration: float = DAY,
    seed: int = 1,
    figures: bool = True,
    progress=None,
    fit_settings: FitSettings | None = None,
    client=None,
) -> dict:
    """Run the scenarios, write ``summary.json``, ``summary.md`` and figures to ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
    cases : iterable of str, optional
        Case names (:data:`PAPER_CASES`); default all.
    variants : iterable of str
        Keys of :data:`VARIANTS`.
    duration : float
        Length of each simulated stretch [s] (the paper: one day).
    seed : int
        Noise seed, shared by every case (same realisation with and without GW).
    client : distributed.Client, optional
        Run the cases on this Dask cluster, one task per variant and base simulation
        (:func:`ttlcore.app.reprocessing.dask_client`); the summary equals the serial run's except
        ``timings_s`` (per variant: the wait for its tasks).

    Returns
    -------
    dict
        The ``summary.json`` content.
    """
    by_name = {c.name: c for c in PAPER_CASES}
    cases = list(by_name) if cases is None else list(cases)
    variants = list(variants)
    fit_settings = _check_scenarios(cases, variants, by_name, duration, fit_settings)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise TTLError(f"--out: {out_dir} exists and is not a directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()

    def say(msg):
        if progress is not None:  # the command's status line shows the elapsed time itself
            progress(msg)

    runner = _Runner(duration, seed, say, fit_settings)
    summary = {"duration_s": duration, "seed": seed, "cases": cases, "variants": {}, "timings_s": {}}
    groups: dict = {}  # cases sharing a base simulation (orbit, t0)
    for cname in cases:
        c = by_name[cname]
        groups.setdefault((c.orbit, c.t0), []).append(c.name)
    futures = {}
    if client is not None:  # one task per (variant, base simulation), results gathered below
        futures = _submit(client, variants, groups, out_dir, (duration, seed, fit_settings, figures))
        say(f"{len(futures)} tasks submitted to {client.scheduler.address}")
    for vname in variants:
        variant = VARIANTS[vname]
        vdir = out_dir / vname
        vdir.mkdir(exist_ok=True)
        rows = []
        t_var = time.monotonic()
        for key, names in groups.items():
            if client is not None:
                rows += futures[vname, key].result()
                say(f"[{vname}] cases {', '.join(names)} done")
            else:
                rows += _run_group(runner, vname, names, vdir, figures)
        rows.sort(key=lambda r: cases.index(r["case"]))
        summary["variants"][vname] = {
            "title": variant["title"],
            "coefficients": variant["coeffs"],
            "jitter_fknee_hz": variant["fknee"],
            "jitter_fhigh_hz": variant.get("fhigh"),
            "cases": rows,
        }
        summary["timings_s"][vname] = round(time.monotonic() - t_var, 1)
    summary["timings_s"]["total"] = round(time.monotonic() - start, 1)
    summary["all_within_limits"] = all(
        r["error_within_limit"] for v in summary["variants"].values() for r in v["cases"]
    )
    write_json(out_dir / "summary.json", summary, indent=1)
    md = _summary_md(summary, duration, seed)
    write_text(out_dir / "summary.md", "".join(md))
    return summary
