"""Figures of ``ttl diagnose``: residual against the expected noise per band, coherence of
the top witnesses (docs/diagnostics.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..estimate.spectra import log_displacement_asd
from ..tdi.combinations import AET
from .batch import _save


def _band_stairs(ax, chi2_dof, edges, fails, marker: str, **style) -> float:
    """chi^2/dof per band as stairs, failing bands marked; returns the top of the values."""
    ax.stairs(chi2_dof, edges, baseline=None, **style)
    centres = np.sqrt(edges[:-1] * edges[1:])
    ax.plot(centres[fails], chi2_dof[fails], marker)
    return float(np.nanmax(chi2_dof))


def _frequency_axes(ax, ylabel: str) -> None:
    """Label, grid and legend of a spectrum's axes (frequency [Hz] along x)."""
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)


def plot_residual_vs_noise(dg, fits: dict, path, tolerance: float = 0.02, fine: dict | None = None) -> Path:
    """Residual ASD of A, E and T (displacement) against the noise model (fitted or fixed),
    and chi^2/dof per band, for each fitted model in ``fits`` (label -> ModelFit); ``fine``
    (label -> :class:`~ttlcore.diagnose.adequacy.BandTable`, third-octave bands) adds the
    finer localisation of the failures."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 10))
    axes = [fig.add_subplot(4, 1, k + 1) for k in range(4)]
    f = dg.grid.f
    for ci, ch in enumerate(AET):
        ax = axes[ci]
        label = "noise model (fitted levels)" if dg.noise.parameters is not None else "instrument noise model"
        ax.loglog(*log_displacement_asd(f, np.real(dg.noise.csd[:, ci, ci])), "k--", lw=1.2, label=label)
        for label, fit in fits.items():
            r = np.linalg.solve(dg.noise.Lh[None], fit.residual_w[..., None])[..., 0]  # unwhiten: r = (L^H)^-1 wr
            p = np.mean(np.abs(r[:, :, ci]) ** 2, axis=0)
            ax.loglog(*log_displacement_asd(f, p), lw=1, label=f"residual ({label})")
        ax.set_ylabel(f"ASD {ch} [m/sqrt(Hz)]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    ax = axes[3]
    edges = dg.grid.edges
    top = 1.2
    for label, fit in fits.items():
        top = max(
            top, 1.1 * _band_stairs(ax, fit.bands.chi2_dof, edges, fit.bands.fails, "rx", lw=1.5, label=label, zorder=3)
        )
    for label, tab in (fine or {}).items():
        top = max(
            top,
            1.1
            * _band_stairs(
                ax, tab.chi2_dof, tab.edges, tab.fails, "r+", lw=0.8, ls=":", label=f"{label}, third-octave", zorder=2
            ),
        )
    ax.axhspan(1 - tolerance, 1 + tolerance, color="0.85", zorder=0, label=f"1 +- tolerance ({100 * tolerance:.0f} %)")
    ax.set_xscale("log")
    ax.set_ylim(0.8, top)
    if top > 5:
        ax.set_yscale("log")
    _frequency_axes(ax, "chi2/dof per band")
    fig.suptitle("Fit residual against the noise model (x, +: failing band)")
    fig.tight_layout()
    return _save(fig, path)


def plot_witness_coherence(witnesses: dict, path) -> Path:
    """Band-averaged coherence of the top witnesses with the whitened residual."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    spec = witnesses["coherence_spectra"]
    f = np.asarray(spec["f"])
    for name, curve in spec["curves"].items():
        y = np.array([np.nan if v is None else v for v in curve])
        ax.semilogx(f, y, lw=1, label=name)
    ax.set_ylim(0, 1)
    _frequency_axes(ax, "coherence with the residual")
    ax.set_title("Top witnesses (whitened, A+E+T)")
    fig.tight_layout()
    return _save(fig, path)
