"""Paper-style figures of a batch analysis (``ttl analyze``): ASDs of TDI X and coefficient
deviations.

Matplotlib is imported lazily, through its object-oriented API with the Agg canvas (no
pyplot, no global backend switch), so importing :mod:`ttlcore` never needs it and figures
can be drawn from any thread.  PNGs are written atomically (temporary name, then rename).

ASDs: one-sided Welch estimates (Hann window, 50 % overlap, segments of 2^16 samples at
4 Hz or shorter for short data), averaged in log-spaced frequency bins for readability
(:func:`ttlcore.estimate.spectra.log_average`, 40 per decade, on the PSD) and converted from
fractional frequency to displacement, ``ASD_x = c ASD_y / (2 pi f)`` (docs/physics.md, units).
The requirement curve is averaged over the same bins, so curves and requirement compare
like with like, also near the zeros of the X2 response (every ~30 mHz).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..conventions import ARM_LENGTH, PAPER_ORDER, paper_ordered_names
from ..estimate.noise_psd import requirement_x2
from ..estimate.spectra import default_nperseg, displacement_asd, log_displacement_asd, longest_run
from ..io.hdf5 import temporary_path

#: Coefficient requirement of the paper [m/rad]: |C_fit - C_true| < 0.1 mm/rad.
COEFFICIENT_REQUIREMENT = 0.1e-3

#: Curves of the ASD figure: series name -> (legend label, matplotlib style).
ASD_CURVES = {
    "data": ("X with TTL", dict(color="black", lw=1.3)),
    "noise_without_ttl": ("X without TTL (true noise)", dict(color="0.6", lw=3.0)),
    "residual": ("residual, fitted coefficients", dict(color="tab:blue", lw=1.3)),
    "residual_true": ("residual, true coefficients", dict(color="#7fbfff", lw=1.5, ls="--")),
    "ttl_residual": ("TTL residual (true TTL - fitted model)", dict(color="tab:green", lw=1.3, ls="-.")),
}
REQUIREMENT_STYLE = dict(color="0.4", lw=1.2, ls="--")


def asd_x_curves(
    sub, channel: str = "X2", nperseg: int | None = None, per_decade: int = 40, arm_length: float = ARM_LENGTH
) -> dict:
    """Log-averaged displacement ASDs [m/sqrt(Hz)] of the series of one channel.

    Parameters
    ----------
    sub : SubtractionResult
    channel : str
        ``"X2"`` (default) or any other channel name.
    nperseg : int, optional
        Welch segment length [samples]; default :func:`default_nperseg`.
    arm_length : float
        For the requirement curve [m].

    Returns
    -------
    dict
        ``{series name: (f, asd)}`` for the series present, plus ``"requirement"``; all on
        the same log-spaced frequencies.  Only samples where every series is finite are used:
        the longest stretch of them (splicing across a gap would put a step in the series and
        leak its power over the band).
    """
    series = sub.channel(channel)
    ok = longest_run(np.all([np.isfinite(v) for v in series.values()], axis=0))
    n = ok.stop - ok.start
    if n < 64:
        raise ValueError(f"too few valid samples ({n}) for an ASD")
    nperseg = nperseg or default_nperseg(n, sub.fs)
    out = {}
    f = None
    for name, x in series.items():
        fc, asd, f = displacement_asd(x[ok], sub.fs, nperseg, per_decade)
        out[name] = (fc, asd)
    assert f is not None, "no series"
    out["requirement"] = log_displacement_asd(f, requirement_x2(f, arm_length), per_decade)
    return out


def _save(fig, path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(path)
    tmp = temporary_path(path)
    FigureCanvasAgg(fig)
    try:
        fig.savefig(tmp, format="png", dpi=130)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def plot_asd_x(
    sub,
    path,
    *,
    band=None,
    arm_length: float = ARM_LENGTH,
    title: str | None = None,
    curves: dict | None = None,
    fmin: float = 1e-4,
    fmax: float = 1.0,
) -> Path:
    """ASD of TDI X in displacement: with TTL (black), residual with the fitted coefficients
    (blue), residual with the true coefficients (light-blue dashed), TTL residual (green
    dash-dotted), noise without TTL (grey), LISA requirement (grey dashed); the fit band is
    shaded.  Curves absent from ``sub`` (no truth) are left out.  Returns the path."""
    from matplotlib.figure import Figure

    curves = curves or asd_x_curves(sub, arm_length=arm_length)
    fig = Figure(figsize=(11, 5.6), layout="constrained")
    ax = fig.add_subplot()
    lo_vals = []
    for name, (label, style) in ASD_CURVES.items():
        if name not in curves:
            continue
        f, asd = curves[name]
        ax.loglog(f, asd, label=label, **style)
        sel = (f >= fmin) & (f <= fmax) & (asd > 0)
        if sel.any():
            lo_vals.append(np.min(asd[sel]))
    f, req = curves["requirement"]
    ax.loglog(f, req, label="LISA requirement", **REQUIREMENT_STYLE)
    if band is not None:
        ax.axvspan(band[0], band[1], color="tab:orange", alpha=0.07, lw=0, label=f"fit band {band[0]:g}-{band[1]:g} Hz")
    sel = (f >= fmin) & (f <= fmax)
    hi = max(np.max(curves["data"][1][(curves["data"][0] >= fmin) & (curves["data"][0] <= fmax)]), np.max(req[sel]))
    lo = min(lo_vals + [np.min(req[sel])])
    ax.set_xlim(fmin, fmax)
    # down to the lowest curve, but not more than two decades below the requirement
    ax.set_ylim(max(lo / 2, np.min(req[sel]) / 100, hi * 1e-8), hi * 3)
    ax.set_xlabel("Frequency [Hz]")
    ax.set_ylabel("ASD of TDI X [m/√Hz]")
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8.5, framealpha=0.9, borderaxespad=0)
    ax.set_title(title or "TDI X", fontsize=10)
    return _save(fig, path)


def _label(name: str) -> str:
    _, angle, side = name.split(".")
    return {"phi": "φ", "eta": "η"}[angle] + " " + side


def plot_coefficients(names, coefficients, sigma, path, *, truth=None, title: str | None = None) -> Path:
    """Coefficient deviations ``fit - truth`` in mm/rad with 1-sigma bars, in the paper's
    order (MOSA 12, 13, 23, 21, 31, 32; each phi rx, phi tx, eta rx, eta tx), with a zero
    line and the +-0.1 mm/rad requirement.  Without ``truth``, the fitted values.  Returns
    the path."""
    from matplotlib.figure import Figure

    names = list(names)
    c = dict(zip(names, np.asarray(coefficients, dtype=float)))
    sig = dict(zip(names, np.asarray(sigma, dtype=float)))
    tru = None if truth is None else dict(zip(names, np.asarray(truth, dtype=float)))
    order = [n for n in paper_ordered_names() if n in c]
    x = np.array([5 * PAPER_ORDER.index(n.split(".")[0]) + (k % 4) for k, n in enumerate(order)], dtype=float)
    y = np.array([c[n] - (tru[n] if tru else 0.0) for n in order]) * 1e3
    e = np.array([sig[n] for n in order]) * 1e3

    fig = Figure(figsize=(10, 4.8), layout="constrained")
    ax = fig.add_subplot()
    if tru is not None:
        ax.axhline(0, color="black", lw=0.8)
        r = COEFFICIENT_REQUIREMENT * 1e3
        ax.axhline(r, color="tab:red", lw=1, ls="--", label=f"±{r:g} mm/rad (paper's goal)")
        ax.axhline(-r, color="tab:red", lw=1, ls="--")
    ax.errorbar(
        x,
        y,
        yerr=e,
        fmt="o",
        ms=4.5,
        color="tab:blue",
        ecolor="tab:blue",
        elinewidth=1.2,
        capsize=3,
        label=("fit - truth" if tru is not None else "fitted value") + ", 1σ bars",
    )
    for g in range(1, len(PAPER_ORDER)):
        ax.axvline(5 * g - 1, color="0.8", lw=0.8, ls=":")
    ax.set_xticks(x, [_label(n) for n in order], fontsize=8, rotation=90)
    centres = [5 * g + 1.5 for g, m in enumerate(PAPER_ORDER) if any(n.startswith(m + ".") for n in order)]
    ax.set_xticks(centres, [f"MOSA {m}" for m in PAPER_ORDER if any(n.startswith(m + ".") for n in order)], minor=True)
    ax.tick_params(axis="x", which="minor", length=0, pad=38, labelsize=9.5)
    ax.set_xlim(-1, 5 * len(PAPER_ORDER) - 1)
    if tru is not None:
        lim = max(0.15, 1.15 * np.max(np.abs(y) + e))
        ax.set_ylim(-lim, lim)
        ax.set_ylabel("C$_{fit}$ − C$_{true}$ [mm/rad]")
    else:  # values near the common size of the coefficients: zoom on them, the bars must show
        lo, hi = np.min(y - e), np.max(y + e)
        pad = max(0.15 * (hi - lo), 0.02)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel("C$_{fit}$ [mm/rad]")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2, fontsize=8.5, frameon=False, borderaxespad=0.2)
    if title:
        ax.set_title(title, fontsize=10, loc="left")
    return _save(fig, path)
