"""``ttl info``: a summary of a telemetry or truth file (options: :mod:`ttlcore.cli.main`)."""

from __future__ import annotations

import numpy as np

from ..conventions import COEFFICIENT_NAMES, LINKS
from ..io.reader import file_kind, read_telemetry
from ..io.truth import read_truth, truth_path
from .report import to_stdout, write_report


def _rms(x: np.ndarray) -> list[float]:
    """RMS of each row over its finite samples (NaN is a gap; NaN if a row has none)."""
    finite = np.isfinite(x)
    count = finite.sum(axis=-1)
    total = np.where(finite, np.square(np.where(finite, x, 0.0)), 0.0).sum(axis=-1)
    return [float(np.sqrt(t / c)) if c else float("nan") for t, c in zip(total, count)]


#: Gap spans printed by ``ttl info`` (all of them are in ``--json``).
SHOWN_SPANS = 8


def gaps(tm) -> dict:
    """The gaps of telemetry ``tm``: samples where an eta or DWS value is missing (NaN), and
    their spans, ``[start, stop)`` in samples and in mission time [s]."""
    missing = tm.missing()
    stretches = tm.nan_stretches()
    return {
        "samples_missing": int(missing.sum()),
        "seconds_missing": float(missing.sum() / tm.fs),
        "fraction_missing": float(missing.mean()) if missing.size else 0.0,
        "stretches": stretches,
        "spans_s": [[tm.t0 + a / tm.fs, tm.t0 + b / tm.fs] for a, b in stretches],
    }


def _gap_lines(s: dict) -> list[str]:
    g = s["gaps"]
    if not g["samples_missing"]:
        return ["  gaps: none"]
    spans = ", ".join(f"{a:.2f}-{b:.2f}" for a, b in g["spans_s"][:SHOWN_SPANS])
    more = len(g["spans_s"]) - SHOWN_SPANS
    lines = [
        f"  gaps: {g['samples_missing']} samples missing (NaN; {g['seconds_missing']:g} s, "
        f"{100 * g['fraction_missing']:.2f} %) in {len(g['spans_s'])} span(s) [s]: {spans}"
        + (f" and {more} more (--json lists them)" if more > 0 else "")
    ]
    file_gaps = s["config"].get("gaps") if s["kind"] == "lisainstrument" else None
    if file_gaps and file_gaps.get("datasets"):
        nan = file_gaps["datasets"]
        lines.append(
            f"  in the file: NaN in {len(nan)} dataset(s) ({sum(d['samples_missing'] for d in nan.values())} samples); "
            f"a beat-note gap reaches {file_gaps['reach_after_s']:g} s further in eta (delay and interpolation), "
            f"an MPR gap {file_gaps['mpr_reach_s']:g} s each side"
            + (
                f"; MPRs interpolated across their gaps: {len(file_gaps['mprs_interpolated'])}"
                if file_gaps.get("mprs_interpolated")
                else ""
            )
        )
    return lines


def summarise(path) -> dict:
    """Summary of a telemetry or truth file as a JSON-serialisable dict."""

    kind = file_kind(path)
    if kind == "truth":
        tr = read_truth(path)
        return {
            "file": str(path),
            "kind": "truth",
            "t0": tr.t0,
            "fs": tr.fs,
            "size": tr.size,
            "duration_s": tr.size / tr.fs,
            "datasets": ["ttl", "coefficients", "angles", "angular_velocity"]
            + [f"noises/{n}" for n in tr.noises]
            + [f"injections/{n}" for n in tr.injections],
            "coefficients_mean_mm_per_rad": dict(
                zip(COEFFICIENT_NAMES, (1e3 * tr.mean_coefficients()).round(6).tolist())
            ),
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
        "gaps": gaps(tm),
        "config": tm.config,
    }
    tp = truth_path(path)
    summary["truth_file"] = str(tp) if tp.exists() else None
    return summary


def run(args) -> int:
    s = summarise(args.file)
    write_report(args.json, s)
    if to_stdout(args.json):
        return 0
    print(f"{s['file']}: {s['kind']} file")
    print(f"  t0 {s['t0']:.3f} s, fs {s['fs']:g} Hz, {s['size']} samples = {s['duration_s'] / 3600:.3f} h")
    if s["kind"] == "truth":
        print("  datasets: " + ", ".join(s["datasets"]))
        print(
            "  mean coefficients [mm/rad]: "
            + " ".join(f"{k}={v:+.4f}" for k, v in s["coefficients_mean_mm_per_rad"].items())
        )
        return 0
    cfg = s["config"]
    if cfg.get("orbit"):
        print(
            f"  orbit {cfg.get('orbit')}, seed {cfg.get('seed')}, noises on: "
            + ", ".join(k for k, v in cfg.get("noises", {}).items() if v)
        )
    print("  link    eta RMS [1]   DWS phi RMS [rad/s]   DWS eta RMS [rad/s]   ltt [s]")
    for link in LINKS:
        print(
            f"  {link}   {s['eta_rms'][link]:.3e}     {s['dws_phi_rms_rad_per_s'][link]:.3e}             "
            f"{s['dws_eta_rms_rad_per_s'][link]:.3e}             {s['ltt_min_s'][link]:.6f} .. {s['ltt_max_s'][link]:.6f}"
        )
    for line in _gap_lines(s):
        print(line)
    print(f"  truth file: {s['truth_file'] or 'none beside it'}")
    return 0
