"""The science subcommands of ``ttl`` (simulate, info, analyze, diagnose, scenarios).

The ``ttl`` entry point is :func:`streamer.cli.main`: it builds this parser with the
operations subcommands added (``build_parser(streamer.cli.register)``), so this package
never imports the operations layer; ``python -m ttlcore.cli`` gives the science commands
alone.

Science subcommands: ``simulate``, ``info``.  Errors print one line naming the file,
dataset or option at fault and exit with status 2; no tracebacks for user errors.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, DAY, LINKS, parse_duration
from ..errors import TTLError
from ..estimate.analyze import analyze, check_band, check_method
from ..estimate.fit import DEFAULT_BAND, FitSettings
from ..gw.scenarios import add_parser as _add_scenarios
from ..io.atomic import write_json
from ..io.reader import file_kind, read_telemetry
from ..io.truth import NOISE_COMPONENTS, read_truth, truth_path
from ..sim.simulator import simulate_to_file
from ..sim.spec import add_simulation_options, simulation_config_from_args
from .diagnose import add_parser as _add_diagnose
from .progress import progress_bar, status_line

log = logging.getLogger("ttl")


# ---------------------------------------------------------------------------
# ttl simulate
# ---------------------------------------------------------------------------

def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate mission telemetry (eta, DWS, delays) and its truth file",
        description="Simulate LISA telemetry at the eta level with TTL coupling (docs/physics.md). "
        "Writes OUT and OUT's truth file (day.h5 -> day.truth.h5).",
    )
    add_simulation_options(p)
    p.add_argument("--out", required=True, help="telemetry file to write (HDF5)")
    p.add_argument("--truth-noises", default="", help="noise components to store alone in the truth file, "
                   "comma-separated (laser, oms, backlink, telescope, test_mass, dws_phi, dws_eta) or 'all'")
    p.add_argument("--chunk", default="3h", help="simulation chunk length (memory bound; the result does not depend on it)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:

    chunk = parse_duration(args.chunk, "--chunk")
    truth_noises = tuple(NOISE_COMPONENTS) if args.truth_noises == "all" else tuple(
        s.strip() for s in args.truth_noises.split(",") if s.strip()
    )
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        raise TTLError(f"--out: directory {out.parent} does not exist")
    config = simulation_config_from_args(args, truth_noises)
    duration = config.duration
    with progress_bar(f"simulate {out.name}", quiet=args.quiet) as progress:
        tpath, rpath = simulate_to_file(config, out, chunk_size=int(round(chunk * args.fs)), progress=progress)
    print(f"wrote {tpath} ({config.size} samples, {duration / DAY:g} d at {args.fs:g} Hz) and {rpath}")
    return 0


# ---------------------------------------------------------------------------
# ttl info
# ---------------------------------------------------------------------------

def _add_info(sub) -> None:
    p = sub.add_parser("info", help="summarise a telemetry file (ours or lisainstrument's) or a truth file")
    p.add_argument("file", help="HDF5 file")
    p.add_argument("--json", metavar="FILE", help="write the summary as JSON to FILE ('-': to standard output, "
                                                  "instead of the text)")
    p.set_defaults(func=_cmd_info)


def _rms(x: np.ndarray) -> list[float]:
    return [float(v) for v in np.sqrt(np.mean(np.square(x), axis=-1))]


def summarise(path) -> dict:
    """Summary of a telemetry or truth file as a JSON-serialisable dict."""

    kind = file_kind(path)
    if kind == "truth":
        tr = read_truth(path)
        return {
            "file": str(path), "kind": "truth", "t0": tr.t0, "fs": tr.fs, "size": tr.size, "duration_s": tr.size / tr.fs,
            "datasets": ["ttl", "coefficients", "angles", "angular_velocity"] + [f"noises/{n}" for n in tr.noises]
            + [f"injections/{n}" for n in tr.injections],
            "coefficients_mean_mm_per_rad": dict(zip(COEFFICIENT_NAMES, (1e3 * tr.mean_coefficients()).round(6).tolist())),
            "ttl_rms": dict(zip(LINKS, _rms(tr.ttl))),
            "injections_rms": {n: float(np.sqrt(np.mean(np.square(v)))) for n, v in tr.injections.items()},
        }
    tm = read_telemetry(path)
    summary = {
        "file": str(path),
        "kind": kind,
        "t0": tm.t0,
        "fs": tm.fs,
        "size": tm.size,
        "duration_s": tm.duration,
        "eta_rms": dict(zip(LINKS, _rms(tm.eta))),
        "dws_phi_rms_rad_per_s": dict(zip(LINKS, _rms(tm.dws_phi))),
        "dws_eta_rms_rad_per_s": dict(zip(LINKS, _rms(tm.dws_eta))),
        "ltt_min_s": dict(zip(LINKS, np.min(tm.ltt, axis=1).tolist())),
        "ltt_max_s": dict(zip(LINKS, np.max(tm.ltt, axis=1).tolist())),
        "config": tm.config,
    }
    tp = truth_path(path)
    summary["truth_file"] = str(tp) if tp.exists() else None
    return summary


def _cmd_info(args) -> int:
    s = summarise(args.file)
    if args.json == "-":
        print(json.dumps(s, indent=2, default=str))
        return 0
    if args.json:
        write_json(args.json, s)

    print(f"{s['file']}: {s['kind']} file")
    print(f"  t0 {s['t0']:.3f} s, fs {s['fs']:g} Hz, {s['size']} samples = {s['duration_s'] / 3600:.3f} h")
    if s["kind"] == "truth":
        print("  datasets: " + ", ".join(s["datasets"]))
        print("  mean coefficients [mm/rad]: " + " ".join(f"{k}={v:+.4f}" for k, v in s["coefficients_mean_mm_per_rad"].items()))
        return 0
    cfg = s["config"]
    if cfg.get("orbit"):
        print(f"  orbit {cfg.get('orbit')}, seed {cfg.get('seed')}, noises on: "
              + ", ".join(k for k, v in cfg.get("noises", {}).items() if v))
    print("  link    eta RMS      DWS phi RMS   DWS eta RMS   ltt [s]")
    for link in LINKS:
        print(f"  {link}   {s['eta_rms'][link]:.3e}   {s['dws_phi_rms_rad_per_s'][link]:.3e}     "
              f"{s['dws_eta_rms_rad_per_s'][link]:.3e}     {s['ltt_min_s'][link]:.6f} .. {s['ltt_max_s'][link]:.6f}")
    print(f"  truth file: {s['truth_file'] or 'none beside it'}")
    return 0


# ---------------------------------------------------------------------------
# ttl analyze
# ---------------------------------------------------------------------------

def _add_analyze(sub) -> None:

    p = sub.add_parser(
        "analyze",
        help="fit the TTL coefficients of a telemetry file, subtract them, write fit.json and figures",
        description="Batch analysis of one telemetry file (ours or lisainstrument's): TDI, fit of the 24 TTL "
        "coefficients, subtraction in the time domain. Writes DIR/fit.json, DIR/asd_X.png and "
        "DIR/coefficients.png. The truth (our truth file, or for lisainstrument data the lisainstrument "
        "file itself) is only used for comparisons, never by the fit.",
    )
    p.add_argument("data", help="telemetry file (HDF5: ours or a lisainstrument measurement file)")
    p.add_argument("--truth", default=None, help="truth file (day.truth.h5), or for lisainstrument data the "
                   "lisainstrument file (its static coefficients; no TTL residual then)")
    p.add_argument("--band", nargs=2, metavar=("FMIN", "FMAX"), default=None,
                   help=f"fit band in Hz (default {DEFAULT_BAND[0]:g} {DEFAULT_BAND[1]:g})")
    p.add_argument("--method", default="gls", help="gls (default) | mcmc")
    p.add_argument("--segment", default=None, help="FFT segment length of the fit, e.g. 6h, 1h or seconds "
                   f"(default {FitSettings().segment_duration:g} s)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=_cmd_analyze)


def _cmd_analyze(args) -> int:

    method = check_method(args.method)
    band = tuple(DEFAULT_BAND) if args.band is None else check_band(args.band)
    settings = FitSettings(band=band)
    if args.segment is not None:
        settings.segment_duration = parse_duration(args.segment, "--segment")
    with status_line("ttl analyze", quiet=args.quiet) as progress:
        out = analyze(args.data, truth_path=args.truth, band=band, method=method, out_dir=args.out,
                      settings=settings, progress=progress)
    res, js = out["fit"], out["fit_json"]
    print(f"{args.data}: {method} fit of {len(res.names)} coefficients over {res.n_segments} segments of "
          f"{settings.segment_duration:g} s, {band[0]:g}-{band[1]:g} Hz: chi2/dof {res.chi2_dof:.3f}, "
          f"median sigma {1e3 * np.median(res.sigma):.4f} mm/rad")
    if "error" in js:
        err = np.array(list(js["error"].values()))
        worst = max(js["error"], key=lambda k: abs(js["error"][k]))
        print(f"  truth ({js['truth_source']}): max |error| {1e3 * np.max(np.abs(err)):.4f} mm/rad ({worst}), "
              f"RMS {1e3 * np.sqrt(np.mean(err ** 2)):.4f} mm/rad, normalised chi2 {js['normalised_chi2']:.1f} for {err.size}")
    req = js.get("asd_x_vs_requirement", {}).get("residual")
    if req:
        print(f"  residual X / requirement in band: median {req['median']:.2f}, max {req['max']:.2f} at {req['f_max']:.3g} Hz")
    for note in js.get("notes", []):
        print(f"  note: {note}")
    print("  wrote " + ", ".join(str(p) for p in out["paths"].values()))
    return 0


# ---------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------

def register(sub) -> None:
    """Add the science subcommands (simulate, info, analyze, diagnose, scenarios) to ``sub``."""
    _add_simulate(sub)
    _add_info(sub)
    _add_analyze(sub)
    _add_diagnose(sub)
    _add_scenarios(sub)


def build_parser(*registrars) -> argparse.ArgumentParser:
    """The ``ttl`` parser: the science subcommands, plus those each of ``registrars`` adds
    (the operations package passes its own: ``ttlcore`` never imports it)."""
    parser = argparse.ArgumentParser(prog="ttl", description="Tilt-to-length noise subtraction for LISA")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in (register, *registrars):
        add(sub)
    return parser


def main(argv=None, registrars=()) -> int:
    """Run one ``ttl`` subcommand; ``registrars`` add subcommands beyond the science ones."""
    parser = build_parser(*registrars)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except (TTLError, ValueError, OSError) as exc:
        print(f"ttl {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ttl {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
