"""``ttl analyze``: fit, subtraction, fit.json and figures of one file (options: :mod:`ttlcore.cli.main`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..app.analysis import analyze, check_band
from ..conventions import parse_duration
from ..estimate.fit import DEFAULT_BAND, FitSettings
from .progress import status_line
from .report import to_stdout, write_report


def run(args) -> int:
    band = tuple(DEFAULT_BAND) if args.band is None else check_band(args.band)
    settings = FitSettings(band=band)
    if args.segment is not None:
        settings = replace(settings, segment_duration=parse_duration(args.segment, "--segment"))
    with status_line("ttl analyze", quiet=args.quiet) as progress:
        out = analyze(
            args.data,
            truth_path=args.truth,
            band=band,
            method=args.method,
            out_dir=args.out,
            settings=settings,
            progress=progress,
        )
    res, js = out["fit"], out["fit_json"]
    write_report(args.json, js)
    if to_stdout(args.json):  # the JSON instead of the text
        return 0
    say = print
    say(
        f"{args.data}: {args.method} fit of {len(res.names)} coefficients over {res.n_segments} segments of "
        f"{settings.segment_duration:g} s, band {band[0]:g}-{band[1]:g} Hz: chi2/dof {res.chi2_dof:.3f}, "
        f"median sigma {1e3 * np.median(res.sigma):.4f} mm/rad"
    )
    loss = js.get("data_loss") or {}
    if loss.get("telemetry_samples_missing"):
        say(
            f"  data lost: {loss['telemetry_samples_missing']} telemetry samples NaN in {len(loss['stretches'])} "
            f"stretch(es), {100 * loss['tdi_fraction_lost']:.2f} % of the TDI samples masked by the fit"
        )
    if "error" in js:
        err = np.array(list(js["error"].values()))
        worst = max(js["error"], key=lambda k: abs(js["error"][k]))
        say(
            f"  truth ({js['truth_source']}): max |error| {1e3 * np.max(np.abs(err)):.4f} mm/rad ({worst}), "
            f"RMS {1e3 * np.sqrt(np.mean(err**2)):.4f} mm/rad, normalised chi2 {js['normalised_chi2']:.1f} "
            f"for {err.size}"
        )
    req = js.get("asd_x_vs_requirement", {}).get("residual")
    if req:
        say(
            f"  residual X / requirement in band: median {req['median']:.2f}, max {req['max']:.2f} "
            f"at {req['f_max']:.3g} Hz"
        )
    for note in js.get("notes", []):
        say(f"  note: {note}")
    if not args.quiet:  # a status line; the report above is the result
        say("  wrote " + ", ".join(str(p) for p in out["paths"].values()))
    return 0
