"""Benchmark: one-day GLS fit and MCMC over the same likelihood.

Simulates one mission day (static unequal arms, all noises, paper coefficients), computes
TDI once (timed separately, not part of the fit), then times

(a) the GLS fit :func:`ttlcore.estimate.fit.fit_tdi` with default :class:`FitSettings`
    (decimation, segment spectra, whitening iterations, sandwich covariance); target 2 s;
(b) :func:`ttlcore.estimate.mcmc.fit_mcmc` on the same segment spectra to 50 autocorrelation
    times, without and with free per-band noise levels; target 60 s each.

Prints one JSON object: the wall times and targets, the coefficient error
``max |C_fit - C_true|`` [mm/rad] of both, and the GLS-vs-MCMC agreement
(``max |C_mcmc - C_gls| / sigma_gls`` and ``max |sigma_mcmc / sigma_gls - 1|`` against the
GLS's model-based covariance, which is the covariance of the sampled likelihood).  If the
GLS fit misses its target (or with ``--profile``) a cProfile breakdown of it is added.

Usage: ``.venv/bin/python bench/fit.py [--duration SECONDS] [--seed N] [--repeat N] [--profile]``
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ttlcore.estimate.fit import FitSettings, fit_tdi  # noqa: E402
from ttlcore.estimate.mcmc import fit_mcmc  # noqa: E402
from ttlcore.sim.coefficients import make_coefficients  # noqa: E402
from ttlcore.sim.simulator import SimulationConfig, simulate  # noqa: E402
from ttlcore.tdi.data import compute_tdi  # noqa: E402

GLS_TARGET_S = 2.0
MCMC_TARGET_S = 60.0

#: Functions of the GLS fit whose cumulative time the profile reports.
PROFILE_STAGES = {
    "segment_spectra (total)": "segment_spectra",
    "  decimation (TDIData.decimated)": "decimated",
    "  segment FFTs (spectra_of_segment)": "spectra_of_segment",
    "fit_spectra (total)": "fit_spectra",
    "  accumulate (normal equations)": "accumulate",
    "  residual_csd (noise re-estimation)": "residual_csd",
    "  sandwich_covariance": "sandwich_covariance",
    "  notch_mask": "notch_mask",
    "  model_csd": "model_csd",
    "  regressor_responses (EIV)": "regressor_responses",
    "  np.linalg.inv (weights)": "inv",
}


def profile_gls(td, settings) -> dict:
    prof = cProfile.Profile()
    prof.enable()
    res, _ = fit_tdi(td, settings)
    prof.disable()
    stats = pstats.Stats(prof).stats
    out = {"iterations": int(res.iterations)}
    for label, func in PROFILE_STAGES.items():
        rows = [v for (fname, _, name), v in stats.items() if name == func and ("ttlcore" in fname or func == "inv")]
        if rows:
            out[label.strip()] = {
                "cumulative_s": round(max(v[3] for v in rows), 3),
                "calls": int(sum(v[1] for v in rows)),
            }
    total = sum(v[2] for v in stats.values())
    out["total_s"] = round(total, 3)
    return out


def agreement(gls, mc) -> dict:
    sig = np.sqrt(np.diag(np.asarray(gls.extra["covariance_model_based"])))
    return {
        "max_abs_mean_difference_over_sigma": round(float(np.max(np.abs(mc.coefficients - gls.coefficients) / sig)), 4),
        "max_abs_sigma_ratio_minus_1": round(float(np.max(np.abs(mc.sigma / sig - 1))), 4),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=86400.0, help="simulated seconds (default one day)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3, help="GLS timing repetitions (the minimum is reported)")
    ap.add_argument("--profile", action="store_true", help="add a cProfile breakdown of the GLS fit")
    args = ap.parse_args()

    coeffs = make_coefficients("paper")
    cfg = SimulationConfig(duration=args.duration, orbit="unequal", coefficients=coeffs, seed=args.seed)
    t = time.perf_counter()
    tm, _ = simulate(cfg)
    t_sim = time.perf_counter() - t
    t = time.perf_counter()
    td = compute_tdi(tm)
    t_tdi = time.perf_counter() - t
    c_true = coeffs.mean(cfg.t0, cfg.t0 + cfg.duration)

    settings = FitSettings()
    gls_times = []
    for _ in range(max(1, args.repeat)):
        t = time.perf_counter()
        gls, internals = fit_tdi(td, settings)
        gls_times.append(time.perf_counter() - t)
    t_gls = min(gls_times)

    spectra = internals["spectra"]
    runs = {}
    for noise_levels in (False, True):
        t = time.perf_counter()
        res, inner = fit_mcmc(spectra, td.ltt_mean, settings, td.names, noise_levels=noise_levels, seed=args.seed)
        runs[noise_levels] = (res, inner["mcmc"], time.perf_counter() - t)

    mm = 1e3
    result = {
        "benchmark": "fit",
        "duration_s": args.duration,
        "cpu_count": os.cpu_count(),
        "simulate_s": round(t_sim, 2),
        "tdi_s": round(t_tdi, 2),
        "gls": {
            "wall_time_s": round(t_gls, 3),
            "wall_times_s": [round(x, 3) for x in gls_times],
            "target_s": GLS_TARGET_S,
            "meets_target": t_gls < GLS_TARGET_S,
            "segments": gls.n_segments,
            "iterations": gls.iterations,
            "chi2_dof": round(gls.chi2_dof, 4),
            "max_abs_error_mm_per_rad": round(float(np.max(np.abs(gls.coefficients - c_true))) * mm, 5),
            "max_sigma_model_based_mm_per_rad": round(
                float(np.max(np.sqrt(np.diag(gls.extra["covariance_model_based"])))) * mm, 5
            ),
        },
    }
    for noise_levels, key in ((False, "mcmc"), (True, "mcmc_noise_levels")):
        res, mc, wall = runs[noise_levels]
        entry = {
            "wall_time_s": round(wall, 2),
            "sampler_wall_time_s": round(mc.wall_time, 2),
            "target_s": MCMC_TARGET_S,
            "meets_target": wall < MCMC_TARGET_S and mc.converged,
            "n_autocorr": 50,
            "converged": mc.converged,
            "nwalkers": mc.nwalkers,
            "n_steps": mc.n_steps,
            "max_autocorr_time": round(float(np.max(mc.autocorr_time)), 1),
            "n_independent": round(mc.n_independent),
            "acceptance_fraction": round(mc.acceptance_fraction, 3),
            "max_abs_error_mm_per_rad": round(float(np.max(np.abs(res.coefficients - c_true))) * mm, 5),
            "agreement_with_gls": agreement(gls, mc),
        }
        if mc.noise_levels is not None:
            entry["noise_levels"] = [round(float(v), 4) for v in mc.noise_levels]
            entry["noise_levels_std"] = [round(float(v), 4) for v in mc.noise_levels_std]
            entry["gls_chi2_dof_per_band"] = [
                round(float(c / d), 4) for c, d in zip(gls.chi2_per_band, gls.dof_per_band)
            ]
        result[key] = entry
    if args.profile or t_gls >= GLS_TARGET_S:
        result["gls_profile"] = profile_gls(td, settings)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
