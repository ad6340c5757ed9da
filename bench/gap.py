"""Benchmark: what a NaN gap costs the rolling fit, against what losing its data explains.

For each seed: 12 h simulated (unequal arms, paper coefficients), streamed hour by hour
through TDIStream into a RollingFit (1-h FFT segments, one-day window, as ``ttl run
--segment 1h``), once clean and once with 10 minutes of NaN in one eta (``eta[0]``, from
5 h 25 min).  For every fit from the gapped segment on it compares the gapped fit with the
clean one per coefficient:

* ``z_clean = (C_gap - C_clean) / sigma_clean`` (what the issue quotes), and
* ``z_loss = (C_gap - C_clean) / sqrt(|sigma_gap^2 - sigma_clean^2|)``: for nested data the
  difference of the two estimates has the variance of the information lost, so ``z_loss``
  is ~N(0, 1) when the gapped fit is as good as its data allows and its sigmas say what
  was lost;

and against the truth the last fit (the whole 12 h): ``sum z^2`` over the 24 coefficients
(chi^2 with 24 degrees of freedom: mean 24, 95 % below 36.4).  Prints JSON: per seed and
in total, the largest |z_clean|, the RMS of z_loss, sum z^2 clean and gapped, the variance
ratio sigma_gap^2 / sigma_clean^2 (median over the coefficients) next to the fraction of
the window's effective samples lost.

Usage: ``PYTHONPATH=$PWD OPENBLAS_NUM_THREADS=1 python bench/gap.py [--seeds 1 2 3 4] [--taper S]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from ttlcore.conventions import DAY  # noqa: E402
from ttlcore.estimate import fit as fit_module  # noqa: E402
from ttlcore.estimate.fit import FitSettings  # noqa: E402
from ttlcore.estimate.rolling import RollingFit  # noqa: E402
from ttlcore.sim.simulator import SimulationConfig, simulate  # noqa: E402
from ttlcore.tdi.data import TDIStream  # noqa: E402

HOURS = 12
GAP_START = 5 * 3600 + 25 * 60  # [s]
GAP = 600.0  # [s]


def hourly_tdi(tm) -> list:
    stream = TDIStream()
    per_hour = int(round(3600 * tm.fs))
    return [stream.push(tm.slice(k * per_hour, (k + 1) * per_hour)) for k in range(tm.size // per_hour)]


def fits(pieces) -> list:
    rf = RollingFit(FitSettings(segment_duration=3600.0), window_duration=DAY)
    out = []
    for td in pieces:
        out.append(rf.push(td))
    return out, rf


def one_seed(seed: int) -> dict:
    cfg = SimulationConfig(duration=HOURS * 3600.0, orbit="unequal", seed=seed)
    tm, _ = simulate(cfg)
    truth = cfg.coefficients.base
    clean = hourly_tdi(tm)
    a = int(GAP_START * tm.fs)
    tm.eta[0, a : a + int(GAP * tm.fs)] = np.nan
    gapped = hourly_tdi(tm)
    fc, _ = fits(clean)
    fg, rf = fits(gapped)
    k_gap = GAP_START // 3600
    valid = [sp.valid_fraction for sp in rf._spectra]  # noqa: SLF001 - the measurement needs it
    z_clean, z_loss, ratio = [], [], []
    for c, g in zip(fc[k_gap:], fg[k_gap:]):
        if c is None or g is None:
            continue
        d = g.coefficients - c.coefficients
        z_clean.append(d / c.sigma)
        z_loss.append(d / np.sqrt(np.abs(g.sigma**2 - c.sigma**2)))
        ratio.append(np.median(g.sigma**2 / c.sigma**2))
    last_c, last_g = fc[-1], fg[-1]
    return {
        "seed": seed,
        "max_abs_z_clean": float(np.max(np.abs(z_clean))),
        "rms_z_loss": float(np.sqrt(np.mean(np.square(z_loss)))),
        "max_abs_z_loss": float(np.max(np.abs(z_loss))),
        "rms_z_loss_per_fit": [round(float(np.sqrt(np.mean(np.square(z)))), 3) for z in z_loss],
        "sum_z2_truth_clean": float(np.sum(((last_c.coefficients - truth) / last_c.sigma) ** 2)),
        "sum_z2_truth_gap": float(np.sum(((last_g.coefficients - truth) / last_g.sigma) ** 2)),
        "variance_ratio_median": [round(float(r), 4) for r in ratio],
        "valid_fraction_gapped_segment": round(float(min(valid)), 4),
        "lost_fraction_of_window": round(float(1 - np.mean(valid)), 4),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    p.add_argument("--taper", type=float, help="half-cosine taper into a gap [s] (default fit.GAP_TAPER)")
    args = p.parse_args(argv)
    if args.taper is not None:
        fit_module.GAP_TAPER = args.taper
    rows = [one_seed(s) for s in args.seeds]
    summary = {
        "max_abs_z_clean": max(r["max_abs_z_clean"] for r in rows),
        "rms_z_loss": float(np.sqrt(np.mean([r["rms_z_loss"] ** 2 for r in rows]))),
        "sum_z2_truth_clean_mean": float(np.mean([r["sum_z2_truth_clean"] for r in rows])),
        "sum_z2_truth_gap_mean": float(np.mean([r["sum_z2_truth_gap"] for r in rows])),
    }
    print(
        json.dumps(
            {
                "benchmark": "gap",
                "hours": HOURS,
                "gap_s": GAP,
                "taper_s": fit_module.GAP_TAPER,
                "seeds": rows,
                "summary": summary,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
