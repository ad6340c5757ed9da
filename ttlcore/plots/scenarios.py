"""Figures of ``ttl scenarios`` (:mod:`ttlcore.app.scenarios`): per case and variant, the X2
ASDs, the coefficient deviations with and without GW and the paper's GW close-up."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, PAPER_ORDER, ffd_to_displacement_asd, paper_ordered_names
from ..estimate.spectra import log_average
from .batch import _save

#: the X2 series of the ASD figures: label and line style
_STYLES = {
    "data": ("X with TTL (and GW)", dict(color="black", lw=1.3)),
    "noise_without_ttl": ("X without TTL", dict(color="0.6", lw=3.0)),
    "residual": ("residual, fitted coefficients", dict(color="tab:blue", lw=1.3)),
    "ttl_residual": ("TTL residual", dict(color="tab:green", lw=1.3, ls="-.")),
    "gw": ("GW response", dict(color="tab:purple", lw=1.3)),
    "ttl_plus_gw_residual": ("TTL + GW only, after subtraction", dict(color="gold", lw=1.6, ls="--")),
}


def scenario_figures(
    case, summary, f, P, fc, req, band, arm, res, ref, truth, out_dir: Path, *, intact_factor: float
) -> dict:
    """The figures of one scenario case (:func:`ttlcore.app.scenarios.analyse_case`):
    ``<case>_asd.png`` (X2 ASDs: data, residual, TTL residual, noise without TTL, GW,
    requirement), ``<case>_coefficients.png`` (deviations with and without GW) and
    ``<case>_gw_intact.png`` (the paper's close-up); returns their paths.

    ``f``, ``P``: Welch frequencies [Hz] and PSDs [1/Hz] of the X2 series by name; ``fc``,
    ``req``: the requirement's frequencies and PSD; ``arm``: mean arm length [m] (the
    displacement scale); ``res``, ``ref``: the fits with and without GW; ``truth``: the true
    coefficients [m/rad]; ``intact_factor``: the GW-over-residual factor of the
    ``gw_intact`` bins (named in the close-up's title)."""
    paths = {}
    names = ["data", "noise_without_ttl", "residual", "ttl_residual", "gw", "ttl_plus_gw_residual"]
    fcl, lp = log_average(f[1:], np.stack([P[k][1:] for k in names]))
    asd = {k: ffd_to_displacement_asd(np.sqrt(lp[i]), fcl) for i, k in enumerate(names)}
    curves = (fcl, asd, fc, ffd_to_displacement_asd(np.sqrt(req), fc))
    title = f"{case.title}: max |error| {summary['max_abs_error_mm']:.4f} mm/rad, chi2/dof {summary['chi2_dof']:.3f}"

    def asd_figure(name: str, keys: list[str], frange: tuple, title: str) -> str:
        return str(_asd_figure(case, curves, band, keys, out_dir / f"{case.name}_{name}.png", frange, title))

    paths["asd"] = asd_figure(
        "asd", ["data", "noise_without_ttl", "residual", "ttl_residual", "gw"], (1e-4, 1.0), title
    )
    if case.gw:
        gi = summary["gw_intact"]
        t2 = (
            f"{case.title}: GW intact: {gi['n_bins']} bins with GW > {intact_factor:g} x TTL residual, "
            f"max deviation {100 * (gi['max_relative_deviation'] or 0):.2f} %"
        )
        keys = ["data", "noise_without_ttl", "residual", "gw", "ttl_plus_gw_residual"]
        paths["gw_intact"] = asd_figure("gw_intact", keys, (1e-4, 3e-2), t2)
    paths["coefficients"] = str(
        _coefficient_figure(case, summary["limit_mm"], res, ref, truth, out_dir / f"{case.name}_coefficients.png")
    )
    return paths


def _asd_figure(case, curves: tuple, band, keys: list[str], path: Path, frange: tuple, title: str):
    """The X2 ASDs ``keys`` (``curves``: their log-averaged frequencies [Hz] and
    displacement ASDs by name, the requirement's frequencies and ASD) between ``frange``
    [Hz], the fit ``band`` shaded; the GW only with a GW in ``case``."""
    from matplotlib.figure import Figure

    fcl, asd, fc, req_x = curves
    fmin, fmax = frange
    fig = Figure(figsize=(10.5, 5.4), layout="constrained")
    ax = fig.add_subplot()
    for k in keys:
        if k == "gw" and not case.gw:
            continue
        label, st = _STYLES[k]
        ax.loglog(fcl, asd[k], label=label, **st)
    ax.loglog(fc, req_x, label="LISA requirement", color="0.4", lw=1.2, ls="--")
    ax.axvspan(band[0], band[1], color="tab:orange", alpha=0.07, lw=0, label=f"fit band {band[0]:g}-{band[1]:g} Hz")
    ax.set_xlim(fmin, fmax)
    sel = (fcl >= fmin) & (fcl <= fmax)
    vals = np.concatenate([asd[k][sel] for k in keys if (k != "gw" or case.gw)] + [req_x[(fc >= fmin) & (fc <= fmax)]])
    vals = vals[vals > 0]
    ax.set_ylim(max(vals.min() / 2, vals.max() * 1e-9), vals.max() * 3)
    ax.set_xlabel("Frequency [Hz]")
    ax.set_ylabel("ASD of TDI X [m/√Hz]")
    ax.grid(True, which="major", alpha=0.35)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8.5, borderaxespad=0)
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def _coefficient_figure(case, lim: float, res, ref, truth, path: Path):
    """The coefficients' deviations from the truth with GW (``res``) and without (``ref``),
    in the paper's order, against the limit ``lim`` [mm/rad]."""
    from matplotlib.figure import Figure

    order = list(paper_ordered_names())
    idx = [COEFFICIENT_NAMES.index(n) for n in order]
    xpos = np.array([5 * PAPER_ORDER.index(n.split(".")[0]) + (k % 4) for k, n in enumerate(order)], dtype=float)
    fig = Figure(figsize=(10, 4.8), layout="constrained")
    ax = fig.add_subplot()
    ax.axhline(0, color="black", lw=0.8)
    ax.axhline(lim, color="tab:red", lw=1, ls="--", label=f"±{lim:g} mm/rad")
    ax.axhline(-lim, color="tab:red", lw=1, ls="--")
    e_ref = 1e3 * (ref.coefficients - truth)[idx]
    e_gw = 1e3 * (res.coefficients - truth)[idx]
    ax.errorbar(
        xpos - 0.15, e_ref, yerr=1e3 * ref.sigma[idx], fmt="o", ms=4, color="0.55", capsize=2.5, label="without GW"
    )
    if case.gw:
        ax.errorbar(
            xpos + 0.15, e_gw, yerr=1e3 * res.sigma[idx], fmt="o", ms=4, color="tab:blue", capsize=2.5, label="with GW"
        )
    ax.set_xticks(xpos, [n.split(".", 1)[1].replace(".", " ") for n in order], fontsize=7, rotation=90)
    for g in range(1, len(PAPER_ORDER)):
        ax.axvline(5 * g - 1, color="0.8", lw=0.8, ls=":")
    ym = max(
        1.2 * lim,
        1.15 * float(np.max(np.abs(e_ref) + 1e3 * ref.sigma[idx])),
        1.15 * float(np.max(np.abs(e_gw) + 1e3 * res.sigma[idx])),
    )
    ax.set_ylim(-ym, ym)
    ax.set_ylabel("C$_{fit}$ − C$_{true}$ [mm/rad]")
    ax.set_title(f"{case.title} (MOSAs {', '.join(PAPER_ORDER)})", fontsize=10, loc="left")
    ax.legend(fontsize=8.5, loc="lower right")
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, path)
